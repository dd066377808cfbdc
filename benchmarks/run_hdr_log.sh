#!/usr/bin/env bash
# Issue 31: does the relative HDR term (--hdr-log-weight W, off by default) pay on the outdoor scenes?
# 10-minute runs (exposure t3, one seed) of Mono-HDR on sky-horizon and backlit-sun at W = 0, 0.01,
# 0.03, 0.1, each a row of OUT/curves.json with its plots beside it (rows already there are not run
# again, so the script resumes). Run it with nothing else on the machine (2 cores):
#   bash benchmarks/run_hdr_log.sh [OUT] ["BACKBONE ..."]
# Default backbones "nerf gs": about 90 minutes each (8 rows of 10 minutes plus evaluations).
set -euo pipefail
export MALLOC_MMAP_THRESHOLD_=33554432 MALLOC_TRIM_THRESHOLD_=17179869184
out=${1:-benchmarks/results/outdoor/hdr_log_10min}
read -ra backbones <<<"${2:-nerf gs}"
for backbone in "${backbones[@]}"; do
    for weight in 0 0.01 0.03 0.1; do
        mono-hdr bench curves --out "$out" --backbones "$backbone" --methods mono \
            --scenes sky-horizon backlit-sun --budget-seconds 600 --eval-points 4 --max-eval-views 8 \
            --set hdr.hdr_log_weight="$weight"
    done
done
