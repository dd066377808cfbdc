"""Train the NeRF and 3DGS backbones with Mono-HDR on one scene under the same time budget,
then print and plot how HDR quality grew with training time for each.

    python examples/compare_backbones.py --scene demo --seconds 120 --out outputs/compare
"""

import argparse
from pathlib import Path

from mono_hdr_plugin.apps.bench.runs import RunBudget, RunSpec, run_row


def compare(
    scene_name: str,
    seconds: float,
    out: Path,
    backbones: tuple[str, ...] = ("nerf", "gs"),
    method: str = "mono",
    eval_points: int = 4,
    max_eval_views: int | None = 4,
) -> list[dict]:
    """One run per backbone (its default preset), same scene, same budget: the benchmark's rows."""
    budget = RunBudget(seconds=seconds, eval_points=eval_points, max_eval_views=max_eval_views)
    return [
        run_row(RunSpec(backbone=backbone, method=method, scene=scene_name), budget, str(out / backbone))
        for backbone in backbones
    ]


def plot(results: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    figure, axis = plt.subplots(figsize=(6, 4))
    for run in results:
        axis.plot(
            [p["train_seconds"] for p in run["curve"]],
            [p["hdr_psnr"] for p in run["curve"]],
            marker="o",
            label=run["spec"]["backbone"],
        )
    axis.set_xlabel("training seconds")
    axis.set_ylabel("HDR mu-law PSNR (dB)")
    axis.grid(alpha=0.3)
    axis.legend()
    figure.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    figure.savefig(path, dpi=120)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scene", default="demo")
    parser.add_argument("--seconds", type=float, default=120.0)
    parser.add_argument("--method", default="mono")
    parser.add_argument("--out", type=Path, default=Path("outputs/compare"))
    args = parser.parse_args()
    results = compare(args.scene, args.seconds, args.out, method=args.method)
    header = f"{'backbone':<8} {'steps':>6} {'seconds':>8} {'HDR PSNR':>9} {'LDR PSNR':>9}"
    print(f"{header} {'fps LDR':>8} {'fps LDR+HDR':>12}")
    for run in results:
        final = run["final"]
        print(
            f"{run['spec']['backbone']:<8} {final['steps']:>6} {final['train_seconds']:>8.1f} "
            f"{final['hdr_psnr']:>9.2f} {final['ldr_psnr']:>9.2f} {run['fps_ldr']:>8.2f} {run['fps_ldr_hdr']:>12.2f}"
        )
    plot(results, args.out / "compare_backbones.png")
    print(f"plot written to {args.out / 'compare_backbones.png'}")


if __name__ == "__main__":
    main()
