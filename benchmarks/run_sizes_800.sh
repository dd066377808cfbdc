#!/usr/bin/env bash
# Issue 32 (real image sizes) at 800 x 800: Mono-HDR-GS with the 3-level image pyramid (the default at
# this size) for 10 minutes on a built-in scene (default demo; exposure t3, 18 training views, one seed),
# the run whose target is "completes, peak memory <= 8 GB". Run it with nothing else on the machine
# (2 cores):
#   bash benchmarks/run_sizes_800.sh [OUT] ["SCENE ..."]
# Each scene is rendered at 800 px first, once (demo in about 45 minutes alone); rows already in OUT's
# curves.json are not run again.
set -euo pipefail
export MALLOC_MMAP_THRESHOLD_=33554432 MALLOC_TRIM_THRESHOLD_=17179869184
out=${1:-benchmarks/results/sizes}
read -ra scenes <<<"${2:-demo}"
mono-hdr bench curves --out "$out/gs800" --backbones gs --methods mono --scenes "${scenes[@]}" \
    --resolution 800 --budget-seconds 600 --eval-points 4 --max-eval-views 8
