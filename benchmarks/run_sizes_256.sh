#!/usr/bin/env bash
# Issue 32 (real image sizes) at 256 x 256: Mono-HDR against the HDR-GS / HDR-NeRF baselines on
# built-in scenes (default demo; exposure t3, 18 training views, one seed, 10 minutes a run), 3DGS
# at full size throughout (the default at 256 px) and, on the first scene only, with a 2-level
# pyramid. Run it with nothing else on the machine (2 cores):
#   bash benchmarks/run_sizes_256.sh [OUT] ["SCENE ..."]
# Each scene is rendered at 256 px first, once (demo in about 5 minutes, lamp-room in 15-22); rows
# already in OUT's curves.json are not run again, so a second scene adds its rows beside the first's.
set -euo pipefail
export MALLOC_MMAP_THRESHOLD_=33554432 MALLOC_TRIM_THRESHOLD_=17179869184
out=${1:-benchmarks/results/sizes}
read -ra scenes <<<"${2:-demo}"
common=(--resolution 256 --budget-seconds 600 --eval-points 4 --max-eval-views 8)
mono-hdr bench curves --out "$out/gs256_full" --backbones gs --methods mono hdr-gs --scenes "${scenes[@]}" \
    "${common[@]}" --set pyramid_levels=1
mono-hdr bench curves --out "$out/nerf256" --backbones nerf --methods mono hdr-nerf --scenes "${scenes[@]}" \
    "${common[@]}"
# 2 levels were the default at 256 px when demo's gs256 rows ran (so their key has no override); these
# curves made the default full size below 512 px.
mono-hdr bench curves --out "$out/gs256" --backbones gs --methods mono hdr-gs --scenes "${scenes[0]}" \
    "${common[@]}" --set pyramid_levels=2
python benchmarks/plot_curves.py "$out/curves_256.png" "$out/gs256" "$out/gs256_full" "$out/nerf256"
