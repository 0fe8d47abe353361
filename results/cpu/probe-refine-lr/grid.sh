#!/usr/bin/env bash
# Test-time refinement: steps x lr, chosen on training scenes (seed-0 12,500-step control).
set -u
cd /work/wt_rf
PY=/work/main/.venv/bin/python
SPLIT=${SPLIT:-train}; N=${N:-30}; SEEDS=${SEEDS:-0}
GRID=${GRID:-"5:0.01 5:0.02 10:0.005 10:0.01 10:0.02 20:0.005 20:0.01 50:0.003"}
for seed in $SEEDS; do
  if [ $seed = 0 ]; then run=/work/runs/ctl_s0/runs/d0154b1382db5c06; data=/work/data0
  else run=/work/runs/ctl_s1/runs/d948a8155cd8e562; data=/work/data1; fi
  for g in $GRID; do
    st=${g%%:*}; lr=${g##*:}
    t0=$(date +%s.%N)
    $PY -m benchmark.tools.refine $run --test $data/cpu/clevr567/$SPLIT --scenes $N --fit input --steps $st --lr $lr --threads 2 > /work/logs/rfc_${SPLIT}_s${seed}_${st}_${lr}.log 2>&1
    t1=$(date +%s.%N)
    cp $run/refine-input.json /work/runs/rfc/${SPLIT}-s${seed}-${st}-${lr}.json
    echo "$SPLIT s$seed $st $lr wall $(echo "$t1 - $t0" | bc)" >> /work/runs/rfc/times.txt
  done
done
echo DONE >> /work/runs/rfc/times.txt
