#!/usr/bin/env bash
# Time to quality on the four other built-in scenes (the demo scene is in run_committed.sh),
# exposure t3, one seed, run with nothing else on the machine (2 cores):
#   bash benchmarks/run_scenes.sh [OUT] [BUDGET_SECONDS]
# 3DGS runs all three methods (Mono-HDR, HDR-GS, HDR-NeRF on the same rasteriser); NeRF runs
# Mono-HDR and HDR-NeRF on the same field (the comparison issue 14 asks for).
set -euo pipefail
export MALLOC_MMAP_THRESHOLD_=33554432 MALLOC_TRIM_THRESHOLD_=17179869184
out=${1:-benchmarks/results/scenes}
budget=${2:-240}
scenes=(lamp-room sunlit-window glossy coloured-light)
mono-hdr bench curves --out "$out/gs" --backbones gs --methods mono hdr-gs hdr-nerf \
    --scenes "${scenes[@]}" --budget-seconds "$budget" --eval-points 6 --max-eval-views 8
mono-hdr bench curves --out "$out/nerf" --backbones nerf --methods mono hdr-nerf \
    --scenes "${scenes[@]}" --budget-seconds "$budget" --eval-points 6 --max-eval-views 8
