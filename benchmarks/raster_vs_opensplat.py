"""OpenSplat's CPU rasteriser and ours, forward + backward, on the same seeded scenes, in one run.

OpenSplat (github pierotofy/OpenSplat, commit 15b7e80) is the maintained 3DGS trainer with a CPU
path. Its timing comes from an anchor script that builds OpenSplat's own CPU sources as a torch
extension and renders a seeded random scene (bench_anchor_opensplat.py, kept outside this
repository); backbones/gs/benchmark.py builds the identical scene for our kernel. The two run
as alternating subprocesses, `--rounds` times each, so machine load hits both alike; the
figure per size is the median over rounds of each run's median of 5.

    OPENSPLAT_DIR=path/to/OpenSplat python benchmarks/raster_vs_opensplat.py \\
        --anchor path/to/opensplat-anchor --out benchmarks/results/raster_vs_opensplat.json
"""

import json
import statistics
import subprocess
import sys
from pathlib import Path

from mono_hdr_plugin.apps.bench import script_args as args_of

SIZES = ((10_000, 128, 128), (50_000, 256, 256))


def run_json(command: list[str]) -> dict:
    output = subprocess.run(command, check=True, capture_output=True, text=True).stdout
    return json.loads(output.strip().splitlines()[-1])


def main() -> None:
    parser = args_of.script_parser(__doc__)
    parser.add_argument("--anchor", type=Path, required=True, help="folder holding bench_anchor_opensplat.py")
    args_of.add_out(parser, Path("benchmarks/results/raster_vs_opensplat.json"))
    args_of.add_count(parser, "--rounds", 3, "timed rounds of each (median)")
    args = parser.parse_args()
    records = []
    for gaussians, height, width in SIZES:
        ours, theirs = [], []
        for _ in range(args.rounds):
            theirs.append(
                run_json(
                    [
                        sys.executable,
                        str(args.anchor / "bench_anchor_opensplat.py"),
                        "--gaussians",
                        str(gaussians),
                        "--height",
                        str(height),
                        "--width",
                        str(width),
                        "--sh-degree",
                        "3",
                        "--mode",
                        "fwd_bwd",
                    ]
                )["fwd_bwd_s"]
            )
            ours.append(
                run_json(
                    [
                        sys.executable,
                        "-c",
                        "import json; from backbones.gs.benchmark import "
                        f"time_training_pass as t; print(json.dumps(t({gaussians}, {height}, {width})))",
                    ]
                )["fwd_bwd_s"]
            )
        record = {
            "gaussians": gaussians,
            "height": height,
            "width": width,
            "opensplat_fwd_bwd_s": statistics.median(theirs),
            "ours_fwd_bwd_s": statistics.median(ours),
            "opensplat_rounds": theirs,
            "ours_rounds": ours,
        }
        record["speedup"] = record["opensplat_fwd_bwd_s"] / record["ours_fwd_bwd_s"]
        records.append(record)
        print(json.dumps(record), flush=True)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(records, indent=2) + "\n")


if __name__ == "__main__":
    main()
