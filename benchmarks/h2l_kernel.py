"""H2L-CC forward + backward: the fused C++ kernel against autograd through the torch layers.

H2L-CC maps every pixel of a training view (3 -> hidden -> 6 -> 3), so on whole images it was most
of a 3DGS step (benchmarks/results/regions/gs_step_profile_512_whole.md: 1044 of 1374 ms went to
H2L-CC and the losses). Both runs in one process, the same weights and inputs, median wall time of
`--repeats` runs after one warm-up, per image side and torch thread count. Writes JSON and Markdown:

    python benchmarks/h2l_kernel.py --out benchmarks/results/h2l_kernel
"""

import argparse
import json
import statistics
import time
from pathlib import Path

import torch

from mono_hdr_plugin.core.converters import H2LColorConverter, h2l_cc, h2l_cc_reference


def step_seconds(convert, converter: H2LColorConverter, side: int, repeats: int) -> float:
    """Median seconds of one forward and backward pass on a side x side image."""
    generator = torch.Generator().manual_seed(side)
    hdr = torch.rand(side, side, 3, generator=generator).requires_grad_()
    target = torch.rand(side, side, 3, generator=generator)
    times = []
    for _ in range(repeats + 1):
        start = time.perf_counter()
        weights = torch.cat([converter.response.weight, converter.bias.weight])
        biases = torch.cat([converter.response.bias, converter.bias.bias])
        out = convert(hdr, converter.latent.weight, converter.latent.bias, weights, biases)
        (out - target).abs().mean().backward()
        times.append(time.perf_counter() - start)
    return statistics.median(times[1:])


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
            fused = step_seconds(h2l_cc, converter, side, args.repeats)
            layers = step_seconds(h2l_cc_reference, converter, side, args.repeats)
            rows.append({"side": side, "threads": threads, "fused_ms": fused * 1e3, "layers_ms": layers * 1e3})
            print(f"{side} px, {threads} thread(s): fused {fused * 1e3:.1f} ms, layers {layers * 1e3:.1f} ms")
    args.out.mkdir(parents=True, exist_ok=True)
    record = {"hidden": args.hidden, "repeats": args.repeats, "rows": rows}
    (args.out / "h2l_kernel.json").write_text(json.dumps(record, indent=2) + "\n")
    lines = [
        f"H2L-CC (hidden {args.hidden}) forward + backward on a side x side image, median of {args.repeats} runs.",
        "",
        "| side (px) | threads | fused C++ (ms) | torch layers (ms) | speed-up |",
        "|---|---|---|---|---|",
    ]
    for row in rows:
        speedup = row["layers_ms"] / row["fused_ms"]
        lines.append(
            f"| {row['side']} | {row['threads']} | {row['fused_ms']:.1f} | {row['layers_ms']:.1f} | {speedup:.1f}x |"
        )
    (args.out / "h2l_kernel.md").write_text("\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
