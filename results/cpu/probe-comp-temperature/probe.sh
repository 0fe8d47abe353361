#!/usr/bin/env bash
# Render probe, no training: the current recipe's 60-minute models (seeds 0 and 1, each on its
# own scenes) scored on all 50 held-out scenes with the slot-guided composition's temperature
# changed at render time (`diagnose --render-set comp_temperature=T`; T < 1 sharpens the soft
# masks m, T > 1 softens them). Does the rim of floor that the object slots claim live in the
# masks' softness or in the object fields' density? Writes seedS_T.json (diagnose's
# failures-probe.json) here. Set SRC0/SRC1 (the 60-minute run folders) and DATA0/DATA1.
set -eu
here=$(cd "$(dirname "$0")" && pwd)
cd "$here/../../.."  # the repository root
runs=${RUNS:-/work/runs}
src0=${SRC0:-$(ls -d $runs/cw_60_s0/runs/*/)}; src1=${SRC1:-$(ls -d $runs/cw_60_s1/runs/*/)}
data0=${DATA0:-/work/wt_l1/data}; data1=${DATA1:-data}
for seed in 0 1; do
  src=$src0; data=$data0
  if [ $seed = 1 ]; then src=$src1; data=$data1; fi
  for T in 1.0 0.5 0.25 2.0; do
    .venv/bin/python -m benchmark.tools.recipe diagnose $src --test $data/cpu/clevr567/test \
      --render-set comp_temperature=$T > /dev/null
    cp $src/failures-probe.json "$here/seed${seed}_T$T.json"
  done
done
