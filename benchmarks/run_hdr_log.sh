#!/usr/bin/env bash
# Issue 31: the runs that chose --hdr-log-weight's outdoor default (0.01; docs/outdoor.md, "The colour
# under a bright sky"). Mono-HDR, exposure t3, one seed, 8 test views, W = 0 / 0.01 / 0.03 given
# explicitly (the default would be 0.01 on these unbounded scenes). Finished rows are kept, so the
# script resumes. Run it with nothing else on the machine (2 cores), about 2 hours:
#   bash benchmarks/run_hdr_log.sh [OUT]
set -euo pipefail
export MALLOC_MMAP_THRESHOLD_=33554432 MALLOC_TRIM_THRESHOLD_=17179869184
out=${1:-benchmarks/results/outdoor}
curves() { mono-hdr bench curves --methods mono --eval-points 4 --max-eval-views 8 "$@"; }
# NeRF, 10 minutes, 2 threads
for weight in 0 0.01 0.03; do
    curves --out "$out/hdr_log_10min" --backbones nerf --scenes backlit-sun sky-horizon --budget-seconds 600 \
        --set hdr.hdr_log_weight="$weight"
done
# 3DGS, 2000 steps, one thread (as ../curves_gs, whose rows are W = 0)
for weight in 0.01 0.03; do
    OMP_NUM_THREADS=1 curves --out "$out/hdr_log_gs" --backbones gs --scenes backlit-sun sky-horizon \
        --budget-steps 2000 --set hdr.hdr_log_weight="$weight"
done
