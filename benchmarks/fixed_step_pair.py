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
"""

import argparse
import json
import os
import subprocess
import sys
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

from mono_hdr_plugin.data.config import DataConfig
from mono_hdr_plugin.data.loading import load_scene

KEYS = ("hdr_psnr", "hdr_psnr_gt_max", "ldr_psnr", "ldr_ssim")
STEPS = {"gs": 300, "nerf": 150}


def run(tree: Path, backbone: str, scene: str, resolution: int | None, out: Path) -> Path:
    """One fixed-step training run of `tree`'s code; its metrics.json (kept from an earlier call)."""
    metrics = out / "metrics.json"
    if metrics.is_file():
        return metrics
    command = [sys.executable, "-m", "mono_hdr_plugin.apps.cli", "train", backbone, "--scene", scene]
    command += ["--max-steps", str(STEPS[backbone]), "--max-eval-views", "4", "--seed", "0"]
    command += ["--out", str(out), "--overwrite", "--quiet"]
    if resolution is not None:
        command += ["--resolution", str(resolution)]
    env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONPATH": str(tree)}
    subprocess.run(command, cwd=tree, env=env, check=True)
    return metrics


def table(rows: list[tuple[str, str, int | None]], out: Path, before_name: str) -> str:
    lines = [
        f"# Fixed-step pair: {before_name} against this tree",
        "",
        f"Each row trains {STEPS['gs']} steps (gs) or {STEPS['nerf']} (nerf) with seed 0 on one thread, "
        "held-out scores of the first 4 test cameras; `same` is equality to every digit of every score.",
        "",
        "| backbone | scene | px | " + " | ".join(f"{key} before | after" for key in KEYS) + " | same |",
        "|" + "---|" * (4 + 2 * len(KEYS)),
    ]
    for backbone, scene, resolution in rows:
        figures = [
            json.loads((out / side / f"{backbone}-{scene}" / "metrics.json").read_text())
            for side in ("before", "after")
        ]
        cells = [f"{figures[0][key]:.4f} | {figures[1][key]:.4f}" for key in KEYS]
        same = all(figures[0][key] == figures[1][key] for key in KEYS)
        size = "default" if resolution is None else str(resolution)
        lines.append(f"| {backbone} | {scene} | {size} | " + " | ".join(cells) + f" | {'yes' if same else 'NO'} |")
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--before", type=Path, required=True, help="a worktree of the earlier commit")
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--backbones", nargs="+", default=["gs", "nerf"])
    parser.add_argument("--scenes", nargs="+", required=True, help="SCENE or SCENE@PX (rendered at PX)")
    args = parser.parse_args()
    here = Path(__file__).resolve().parents[1]
    rows = []
    for item in args.scenes:
        scene, _, px = item.partition("@")
        rows += [(backbone, scene, int(px) if px else None) for backbone in args.backbones]
    jobs = [
        (tree, backbone, scene, resolution, args.out.resolve() / side / f"{backbone}-{scene}")
        for backbone, scene, resolution in rows
        for side, tree in (("before", args.before.resolve()), ("after", here))
    ]
    for scene, resolution in dict.fromkeys((scene, resolution) for _, scene, resolution in rows):
        load_scene(DataConfig(scene=scene, resolution=resolution))  # rendered once, before two runs want it
    with ThreadPoolExecutor(2) as pool:
        list(pool.map(lambda job: run(*job), jobs))
    commit = subprocess.run(
        ["git", "-C", str(args.before), "rev-parse", "--short", "HEAD"], capture_output=True, text=True, check=True
    ).stdout.strip()
    report = table(rows, args.out, commit)
    (args.out / "pair.md").write_text(report)
    print(report)


if __name__ == "__main__":
    main()
