#!/usr/bin/env bash
# The commands behind the committed figures in benchmarks/results/ and docs/, run one after
# another with nothing else on the machine (2 cores): seconds are wall-clock on a quiet machine,
# and `curves` is time-budgeted, so its quality figures depend on the machine being otherwise idle.
#   bash benchmarks/run_committed.sh [OUT] [BUDGET_SECONDS]
# OpenSplat's anchor needs its sources (see benchmarks/raster_vs_opensplat.py): set OPENSPLAT_DIR
# and ANCHOR_DIR to run that comparison, it is skipped otherwise.
set -euo pipefail
export MALLOC_MMAP_THRESHOLD_=33554432 MALLOC_TRIM_THRESHOLD_=17179869184
out=${1:-benchmarks/results}
budget=${2:-300}
mono-hdr bench raster --out "$out" --repeats 7
if [[ -n "${OPENSPLAT_DIR:-}" && -n "${ANCHOR_DIR:-}" ]]; then
    python benchmarks/raster_vs_opensplat.py --anchor "$ANCHOR_DIR" --out "$out/raster_vs_opensplat.json"
fi
python benchmarks/gs_step_profile.py --scene demo --warmup 300 --repeats 11 --out "$out/gs_step_profile.md"
mono-hdr bench curves --out "$out" --scenes demo --budget-seconds "$budget" --eval-points 6 --max-eval-views 8
