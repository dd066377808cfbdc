#!/usr/bin/env bash
# Issue 45: opensfm_lund (29 phone photos down a street, auto exposure, EXIF and GPS; third-party
# data read in place from shared/data/real beside the project) from folder to a trained model.
# process-data, then Mono-HDR-GS for SECONDS seconds at half size (516 x 385) with camera pose
# refinement on and off; held-out views are every 8th photo. Finished runs are kept (the script
# resumes). Run with nothing else on the machine:
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
for opt in on off; do
    [ -f "$out/camera-opt-$opt/metrics.json" ] && continue
    mono-hdr train gs --data "$scratch/data" --downscale 2 --max-seconds "$seconds" --camera-opt "$opt" \
        --seed 0 --quiet --out "$scratch/camera-opt-$opt" --overwrite
    mkdir -p "$out/camera-opt-$opt"
    cp "$scratch/camera-opt-$opt"/*.json "$out/camera-opt-$opt/"
done
python benchmarks/real_photos.py --out "$out"
