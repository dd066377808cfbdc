"""The per-pixel parts of a 3DGS training step, fused C++ kernel against autograd through torch layers.

H2L-CC (3 -> hidden -> 6 -> 3 on every pixel) and the three D-SSIM losses were most of a whole-image
step (benchmarks/results/regions/gs_step_profile_512_whole.md: 1044 of 1374 ms). Each kernel and its
torch twin run in one process on the same inputs: median wall time of `--repeats` forward and
backward passes after one warm-up, per image side and torch thread count. Writes JSON and Markdown:

    python benchmarks/loss_kernels.py --out benchmarks/results/loss_kernels
"""

import argparse
import json
import statistics
import time
from collections.abc import Callable
from pathlib import Path

import torch
from torch import Tensor

from mono_hdr_plugin.core.converters import H2LColorConverter, h2l_cc, h2l_cc_reference
from mono_hdr_plugin.core.metrics import ssim_map, ssim_map_reference


def median_seconds(loss: Callable[[], Tensor], repeats: int) -> float:
    """Median seconds of computing `loss()` and its backward pass."""
    times = []
    for _ in range(repeats + 1):
        start = time.perf_counter()
        loss().backward()
        times.append(time.perf_counter() - start)
    return statistics.median(times[1:])


def h2l_loss(convert, converter: H2LColorConverter, hdr: Tensor, target: Tensor) -> Callable[[], Tensor]:
    def loss() -> Tensor:
        weights = torch.cat([converter.response.weight, converter.bias.weight])
        biases = torch.cat([converter.response.bias, converter.bias.bias])
        return (convert(hdr, converter.latent.weight, converter.latent.bias, weights, biases) - target).abs().mean()

    return loss


def ssim_loss(mapper, pred: Tensor, target: Tensor) -> Callable[[], Tensor]:
    return lambda: 1.0 - mapper(pred, target).mean()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sides", type=int, nargs="+", default=[128, 512, 1024])
    parser.add_argument("--threads", type=int, nargs="+", default=[1, 2])
    parser.add_argument("--hidden", type=int, default=128)
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args()
    converter = H2LColorConverter(args.hidden)
    rows = []
    for threads in args.threads:
        torch.set_num_threads(threads)
        for side in args.sides:
            generator = torch.Generator().manual_seed(side)
            pred = torch.rand(side, side, 3, generator=generator).requires_grad_()
            target = torch.rand(side, side, 3, generator=generator)
            pairs = {
                "H2L-CC": (
                    h2l_loss(h2l_cc, converter, pred, target),
                    h2l_loss(h2l_cc_reference, converter, pred, target),
                ),
                "D-SSIM": (ssim_loss(ssim_map, pred, target), ssim_loss(ssim_map_reference, pred, target)),
            }
            for part, (fused, layers) in pairs.items():
                row = {"part": part, "side": side, "threads": threads}
                row["fused_ms"] = median_seconds(fused, args.repeats) * 1e3
                row["layers_ms"] = median_seconds(layers, args.repeats) * 1e3
                rows.append(row)
                times = f"fused {row['fused_ms']:.1f} ms, torch {row['layers_ms']:.1f} ms"
                print(f"{part}, {side} px, {threads} thread(s): {times}")
    args.out.mkdir(parents=True, exist_ok=True)
    record = {"hidden": args.hidden, "repeats": args.repeats, "rows": rows}
    (args.out / "loss_kernels.json").write_text(json.dumps(record, indent=2) + "\n")
    lines = [
        f"Forward + backward on a side x side x 3 image, median of {args.repeats} runs (H2L-CC hidden {args.hidden}).",
        "",
        "| part | side (px) | threads | fused C++ (ms) | torch layers (ms) | speed-up |",
        "|---|---|---|---|---|---|",
    ]
    for row in rows:
        speedup = row["layers_ms"] / row["fused_ms"]
        lines.append(
            f"| {row['part']} | {row['side']} | {row['threads']} | {row['fused_ms']:.1f} | {row['layers_ms']:.1f} "
            f"| {speedup:.1f}x |"
        )
    (args.out / "loss_kernels.md").write_text("\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
