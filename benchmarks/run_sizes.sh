#!/usr/bin/env bash
# Issue 32 (real image sizes): Mono-HDR-GS and Mono-HDR-NeRF against the HDR-GS / HDR-NeRF baselines on
# built-in scenes (default demo) at 512 x 512 (exposure t3, 18 training views, one seed), 3DGS with the
# 3-level image pyramid (the default at 512 px) and Mono-HDR-GS also at full size, then the cost table
# (ms per step, render and evaluation time, peak memory) from 128 to 800 px and 18 to 108 views.
# Each command is its own process (its peak memory is its own); run it with nothing else on the
# machine (2 cores):
#   bash benchmarks/run_sizes.sh [OUT] ["SCENE ..."]
# Each scene is rendered at 512 px first, once (demo: 20 minutes alone, lamp-room about 70); rows already in OUT's
# curves.json are not run again, so a second scene adds its rows beside the first's.
set -euo pipefail
export MALLOC_MMAP_THRESHOLD_=33554432 MALLOC_TRIM_THRESHOLD_=17179869184
out=${1:-benchmarks/results/sizes}
read -ra scenes <<<"${2:-demo}"
common=(--scenes "${scenes[@]}" --resolution 512 --eval-points 4 --max-eval-views 8)
# Full size throughout against the 3-level pyramid (the default at 512 px since these figures; the
# committed gs512 row was run before, when full size was the default, so its key has no override).
mono-hdr bench curves --out "$out/gs512" --backbones gs --methods mono --budget-seconds 600 "${common[@]}" \
    --set pyramid_levels=1
mono-hdr bench curves --out "$out/gs512_pyramid" --backbones gs --methods mono hdr-gs --budget-seconds 600 \
    "${common[@]}" --set pyramid_levels=3
mono-hdr bench curves --out "$out/nerf512" --backbones nerf --methods mono hdr-nerf --budget-seconds 1200 \
    "${common[@]}"
mono-hdr bench cost --out "$out/cost"
python benchmarks/plot_curves.py "$out/curves_512.png" "$out/gs512" "$out/gs512_pyramid" "$out/nerf512"
