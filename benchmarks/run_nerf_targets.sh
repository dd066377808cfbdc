#!/usr/bin/env bash
# Issue 14's NeRF targets: Mono-HDR-NeRF and HDR-NeRF on the same field (cpu preset), every
# built-in studio scene but textured-desk, 10 minutes of training a run, exposure t3, one seed.
# The two methods run side by side, one core and one torch thread each, so each scene's pair
# shares the machine equally; run it with nothing else on the machine (2 cores):
#   bash benchmarks/run_nerf_targets.sh [OUT] [BUDGET_SECONDS]
set -euo pipefail
export MALLOC_MMAP_THRESHOLD_=33554432 MALLOC_TRIM_THRESHOLD_=17179869184
out=${1:-benchmarks/results/nerf_targets}
budget=${2:-600}
scenes=(demo lamp-room sunlit-window glossy coloured-light)
pids=()
for method in mono hdr-nerf; do
    mono-hdr bench curves --out "$out/$method" --backbones nerf --methods "$method" --scenes "${scenes[@]}" \
        --budget-seconds "$budget" --eval-points 6 --max-eval-views 8 --cpus-per-run 1 &
    pids+=($!)
done
for pid in "${pids[@]}"; do wait "$pid"; done  # fails if either run failed
# both methods in one plot
python - "$out" <<'PY'
import json, sys
from pathlib import Path
from mono_hdr_plugin.apps.bench.curves import plot_curves
out = Path(sys.argv[1])
rows = [row for method in ("mono", "hdr-nerf") for row in json.loads((out / method / "curves.json").read_text())["rows"].values()
        if row["status"] == "ok"]
plot_curves(rows, out / "curves.png")
PY
