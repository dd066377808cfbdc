"""The fixed-step before/after pair a change of the default training owes: the same `mono-hdr train`
rows run on an earlier commit's tree and on this one, a fixed number of steps each, and their
metrics compared to every digit. A fixed step count is deterministic for a given thread count, so a
change that leaves the studio's training alone gives the same numbers.

    git worktree add /tmp/before COMMIT
    python benchmarks/fixed_step_pair.py --before /tmp/before --out benchmarks/results/NAME \\
        --scenes demo lamp-room --backbones gs nerf

Each run uses one torch thread (two run side by side); the earlier tree is put first on PYTHONPATH,
so both use this environment's packages and kernels. Finished runs are kept (the script resumes).
Writes OUT/{before,after}/<backbone>-<scene>/metrics.json and OUT/pair.md.

Repeatability (docs/testing.md): `--before .` runs this tree twice, and `--threads 2` runs each run
on two threads, one run at a time:

    python benchmarks/fixed_step_pair.py --before . --threads 2 --out benchmarks/results/repeatability \
        --scenes demo
"""

import argparse
import json
import math
import os
import subprocess
import sys
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

from mono_hdr_plugin.data.config import DataConfig
from mono_hdr_plugin.data.loading import load_scene

KEYS = ("hdr_psnr", "hdr_psnr_gt_max", "ldr_psnr", "ldr_ssim")
STEPS = {"gs": 300, "nerf": 150}


def run(tree: Path, backbone: str, scene: str, resolution: int | None, out: Path, threads: int) -> Path:
    """One fixed-step training run of `tree`'s code; its metrics.json (kept from an earlier call)."""
    metrics = out / "metrics.json"
    if metrics.is_file():
        return metrics
    command = [sys.executable, "-m", "mono_hdr_plugin.apps.cli", "train", backbone, "--scene", scene]
    command += ["--max-steps", str(STEPS[backbone]), "--max-eval-views", "4", "--seed", "0"]
    command += ["--out", str(out), "--overwrite", "--quiet"]
    if resolution is not None:
        command += ["--resolution", str(resolution)]
    env = {**os.environ, "OMP_NUM_THREADS": str(threads), "PYTHONPATH": str(tree)}
    subprocess.run(command, cwd=tree, env=env, check=True)
    return metrics


TIMINGS = ("train_seconds",)
"""Keys of metrics.json that time the run, not score it: they differ between any two runs."""


def scores(metrics: dict) -> dict[str, float]:
    """Every score of a metrics.json, per-exposure tables flattened (`ldr_psnr_per_exposure/0.5`)."""
    flat = {}
    for key, value in metrics.items():
        if isinstance(value, dict):
            flat.update({f"{key}/{inner}": number for inner, number in value.items() if isinstance(number, float)})
        elif isinstance(value, float) and key not in TIMINGS:
            flat[key] = value
    return flat


def largest_difference(before: dict, after: dict) -> float:
    """The largest relative difference between two metrics.json files over every score both hold
    (0: the same to every digit)."""
    first, second = scores(before), scores(after)
    differences = [
        abs(first[key] - second[key]) / max(abs(first[key]), 1e-12)
        for key in first.keys() & second.keys()
        if first[key] != second[key] and not (math.isnan(first[key]) and math.isnan(second[key]))
    ]
    return max(differences, default=0.0)


def table(rows: list[tuple[str, str, int | None]], out: Path, before_name: str, threads: int) -> str:
    lines = [
        f"# Fixed-step pair: {before_name} against this tree",
        "",
        f"Each row trains {STEPS['gs']} steps (gs) or {STEPS['nerf']} (nerf) with seed 0 on {threads} "
        "thread(s), held-out scores of the first 4 test cameras; `largest difference` is the largest relative "
        "difference over every score in metrics.json (0: the same to every digit).",
        "",
        "| backbone | scene | px | " + " | ".join(f"{key} before | after" for key in KEYS) + " | largest difference |",
        "|" + "---|" * (4 + 2 * len(KEYS)),
    ]
    for backbone, scene, resolution in rows:
        figures = [
            json.loads((out / side / f"{backbone}-{scene}" / "metrics.json").read_text())
            for side in ("before", "after")
        ]
        cells = [f"{figures[0][key]:.4f} | {figures[1][key]:.4f}" for key in KEYS]
        size = "default" if resolution is None else str(resolution)
        difference = largest_difference(*figures)
        lines.append(f"| {backbone} | {scene} | {size} | " + " | ".join(cells) + f" | {difference:.2g} |")
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--before", type=Path, required=True, help="a worktree of the earlier commit")
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--backbones", nargs="+", default=["gs", "nerf"])
    parser.add_argument("--scenes", nargs="+", required=True, help="SCENE or SCENE@PX (rendered at PX)")
    parser.add_argument("--threads", type=int, default=1, help="torch threads a run; above 1, one run at a time")
    args = parser.parse_args()
    here = Path(__file__).resolve().parents[1]
    rows = []
    for item in args.scenes:
        scene, _, px = item.partition("@")
        rows += [(backbone, scene, int(px) if px else None) for backbone in args.backbones]
    jobs = [
        (tree, backbone, scene, resolution, args.out.resolve() / side / f"{backbone}-{scene}", args.threads)
        for backbone, scene, resolution in rows
        for side, tree in (("before", args.before.resolve()), ("after", here))
    ]
    for scene, resolution in dict.fromkeys((scene, resolution) for _, scene, resolution in rows):
        load_scene(DataConfig(scene=scene, resolution=resolution))  # rendered once, before two runs want it
    with ThreadPoolExecutor(2 if args.threads == 1 else 1) as pool:
        list(pool.map(lambda job: run(*job), jobs))
    commit = subprocess.run(
        ["git", "-C", str(args.before), "rev-parse", "--short", "HEAD"], capture_output=True, text=True, check=True
    ).stdout.strip()
    report = table(rows, args.out, commit, args.threads)
    (args.out / "pair.md").write_text(report)
    print(report)


if __name__ == "__main__":
    main()
