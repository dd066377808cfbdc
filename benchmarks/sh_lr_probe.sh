#!/usr/bin/env bash
# The probe behind benchmarks/results/sh_lr_probe/: both 3DGS methods on `demo` (t3, 500 steps)
# with 10x 3DGS's SH DC learning rate. Quality depends on steps only; the committed run shared
# the cores with a test suite, so its train_seconds are not comparable with paper.json.
set -euo pipefail
out=${1:-benchmarks/results/sh_lr_probe}
mkdir -p "$out"
for method in hdr-gs mono; do
  run=$(mktemp -d)
  mono-hdr train gs --scene demo --method "$method" --max-steps 500 --backbone.lr-sh-dc 0.025 --out "$run"
  cp "$run/metrics.json" "$out/$method.json"
  rm -rf "$run"
done
