#!/usr/bin/env bash
# The paper's tables sized for this project's 2-core machine (about 80 minutes, nothing else
# running): Table 1 on both backbones over 3 seeds, the converter ablation on 1 seed, and the
# shared-versus-tuned recipe table (8 trials a method, tuned on demo, reported on lamp-room);
# scenes demo and lamp-room, exposure t3, 120 s of training a run, two runs at a time on Ray
# with one CPU each. Left out of the full grid: three scenes, t1/t5, the loss and ratio
# ablations, and two ablation seeds (README, "The paper's tables").
#   bash benchmarks/run_paper.sh [OUT]
set -euo pipefail
out=${1:-benchmarks/results/paper}
mono-hdr bench paper --out "$out" --scenes demo lamp-room --exposure-indices 1 --seeds 0 1 2 \
    --ablation-seeds 0 --tables table1 converters recipes --budget-seconds 120 \
    --executor ray --cpus-per-run 1
