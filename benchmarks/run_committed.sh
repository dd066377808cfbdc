#!/usr/bin/env bash
# The commands behind benchmarks/results/, run one after another with nothing else on the
# machine (2 cores): seconds are wall-clock on a quiet machine, and `curves` is time-budgeted,
# so its quality figures depend on the machine being otherwise idle.
set -euo pipefail
export MALLOC_MMAP_THRESHOLD_=33554432 MALLOC_TRIM_THRESHOLD_=17179869184
out=${1:-benchmarks/results}
mono-hdr bench paper --out "$out" --steps 500 --exposure-indices 1
mono-hdr bench raster --out "$out" --repeats 3
mono-hdr bench curves --out "$out" --budget-seconds 150 --eval-points 5 --max-eval-views 8
