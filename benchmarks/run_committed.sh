#!/usr/bin/env bash
# The commands behind benchmarks/results/. In the committed run, `paper` ran in one process
# while `raster` and then `curves` ran in a second one on the same 2 cores, so seconds in
# all three files are measured under that shared load (quality figures depend on steps only,
# except in `curves`, whose runs are time-budgeted).
set -euo pipefail
export MALLOC_MMAP_THRESHOLD_=33554432 MALLOC_TRIM_THRESHOLD_=17179869184
out=${1:-benchmarks/results}
mono-hdr bench paper --out "$out" --gs-steps 500 --nerf-steps 500 --exposure-indices 1 &
{ mono-hdr bench raster --out "$out"
  mono-hdr bench curves --out "$out" --budget-seconds 60 --eval-points 3 --max-eval-views 4; }
wait
