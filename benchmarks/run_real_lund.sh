#!/usr/bin/env bash
# Issue 45: opensfm_lund (29 phone photos down a street, auto exposure, EXIF and GPS; third-party
# data read in place from shared/data/real beside the project) from folder to a trained model.
# process-data, then Mono-HDR-GS for SECONDS seconds at half size (516 x 385), held-out views every
# 8th photo, each scored as given and with the held-out protocol (appearance fitted on the left half
# of the photo, scored on the right half: docs/own_photos.md):
#   baseline       no per-view white balance, no pose refinement (exposures learned, as EXIF allows)
#   white-balance  three gains per view learned with the model
#   camera-opt     white balance and pose refinement (--camera-opt-lr 1e-3)
#   nerf           Mono-HDR-NeRF with white balance
#   hdr-gs         the HDR-GS baseline with white balance
#   prior-1        the baseline with the HDR prior at weight 1 (the default without HDR views is 0.1)
# Finished runs are kept (the script resumes). Run with nothing else on the machine:
#   bash benchmarks/run_real_lund.sh [OUT] [SECONDS]
set -euo pipefail
export MALLOC_MMAP_THRESHOLD_=33554432 MALLOC_TRIM_THRESHOLD_=17179869184
out=${1:-benchmarks/results/real_photos/lund}
seconds=${2:-600}
photos=$(cd "$(dirname "$0")/../.." && pwd)/shared/data/real/opensfm_lund/images
scratch=${SCRATCH:-/tmp/mono-hdr-lund}
mkdir -p "$out" "$scratch"
if [ ! -f "$scratch/data/process_data.json" ]; then
    start=$(date +%s.%N)
    mono-hdr process-data --images "$photos" --out "$scratch/data" --overwrite
    echo "{\"process_data_seconds\": $(echo "$(date +%s.%N) - $start" | bc)}" > "$out/process_data_time.json"
fi
cp "$scratch/data/process_data.json" "$out/process_data.json"
declare -A flags=(
    [baseline]="gs --learn-white-balance off --camera-opt off"
    [white-balance]="gs --learn-white-balance on --camera-opt off"
    [camera-opt]="gs --learn-white-balance on --camera-opt on --camera-opt-lr 1e-3"
    [nerf]="nerf --learn-white-balance on --camera-opt off"
    [hdr-gs]="gs --method hdr-gs --learn-white-balance on --camera-opt off"
    [prior-1]="gs --learn-white-balance off --camera-opt off --hdr-prior-weight 1"
)
for run in ${RUNS:-baseline white-balance camera-opt nerf hdr-gs prior-1}; do
    [ -f "$out/$run/metrics.json" ] && continue
    # shellcheck disable=SC2086
    mono-hdr train ${flags[$run]} --data "$scratch/data" --downscale 2 --max-seconds "$seconds" \
        --eval-appearance on --seed 0 --quiet --out "$scratch/$run" --overwrite
    mkdir -p "$out/$run"
    cp "$scratch/$run"/*.json "$out/$run/"
done
python benchmarks/real_photos.py --out "$out"
