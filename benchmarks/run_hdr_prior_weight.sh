#!/usr/bin/env bash
# Issue 44: the runs that chose --hdr-prior-weight's default (docs/method.md, "HDR without HDR views").
# Mono-HDR-GS, no HDR views (--hdr-view-ratio 1:0), exposure t3, seed 0, 1000 steps, L_prior weight W.
# Chosen on CHOOSE, confirmed on CONFIRM (which takes no part in the choice). Finished runs are kept,
# so the script resumes. Run with nothing else on the machine; about 1 minute a run on 2 cores:
#   bash benchmarks/run_hdr_prior_weight.sh [OUT]
set -euo pipefail
export MALLOC_MMAP_THRESHOLD_=33554432 MALLOC_TRIM_THRESHOLD_=17179869184
out=${1:-benchmarks/results/hdr_prior/weight}
CHOOSE="demo lamp-room"
CONFIRM="textured-desk"
WEIGHTS="0.03 0.1 0.3"
run() {  # scene weight
    [ -f "$out/$2/$1/metrics.json" ] && return
    mono-hdr train gs --scene "$1" --hdr-view-ratio 1:0 --hdr-prior-weight "$2" --max-steps 1000 \
        --max-eval-views 8 --quiet --out "$out/$2/$1" --overwrite
}
for scene in $CHOOSE $CONFIRM; do
    for weight in $WEIGHTS; do run "$scene" "$weight"; done
done
python benchmarks/hdr_prior_weight.py --out "$out" --choose $CHOOSE --confirm $CONFIRM
