#!/usr/bin/env bash
# The control arm of the fine-tune probes at the slot-distillation arm's step count:
# 3.55 minutes (about 1,150 steps) instead of 8; seeds 0 and 1 side by side, 1 thread each.
set -u
cd /work/wt_sd
PY=/work/main/.venv/bin/python
echo "start $(date -u +%H:%M:%S)"
for seed in 0 1; do
  if [ $seed = 0 ]; then src=/work/runs/ctl_s0/runs/d0154b1382db5c06; data=/work/data0
  else src=/work/runs/ctl_s1/runs/d948a8155cd8e562; data=/work/data1; fi
  $PY -m benchmark.tools.recipe train-eval --data $data/cpu/clevr567/train --test $data/cpu/clevr567/test --minutes 3.55 --init-from $src --threads 1 --eval-every 0 --grid-scenes 6 --seed $seed --lr 4e-4 --out /work/runs/pctl1k_s${seed} > /work/logs/pctl1k_s${seed}.log 2>&1 &
done
wait
echo "all done $(date -u +%H:%M:%S)"
