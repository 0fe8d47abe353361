#!/usr/bin/env bash
# Fine-tune probe of photo_l1: the recipe's 60-minute models (seed 0: 17,804 steps, seed 1:
# 16,519 steps) trained 10 more minutes, two arms side by side (1 thread each), with and
# without the absolute-error photometric term from the first step; the locality radius fixed
# at its end value (0.5). Then `diagnose` on each arm.
set -u
cd "$(dirname "$0")/../../.."  # the repository root
runs=${RUNS:-/work/runs}; logs=${LOGS:-/work/logs}
for seed in 0 1; do
  src=$([ $seed = 0 ] && echo ${SRC0:-$runs/nar5_60_s0/runs/5a8e09280de15076} || echo ${SRC1:-$runs/nar5_60_s1/runs/a684e418b9a6e286})
  common="train-eval --data data/cpu/clevr567/train --test data/cpu/clevr567/test --minutes ${MIN:-10} --init-from $src --threads 1 --eval-every 0 --grid-scenes 6 --model-set slot_locality=0.5 --model-set slot_locality_narrow=null"
  echo "seed $seed start $(date -u +%H:%M:%S)"
  .venv/bin/python -m benchmark.tools.recipe $common --out $runs/pl1_s${seed}_ctrl > $logs/pl1_s${seed}_ctrl.log 2>&1 &
  .venv/bin/python -m benchmark.tools.recipe $common --out $runs/pl1_s${seed}_l1 --model-set 'photo_l1=[0.0,0.0]' > $logs/pl1_s${seed}_l1.log 2>&1 &
  wait
  echo "seed $seed done $(date -u +%H:%M:%S)"
done
for r in s0_ctrl s0_l1 s1_ctrl s1_l1; do
  .venv/bin/python -m benchmark.tools.recipe diagnose $runs/pl1_$r --test data/cpu/clevr567/test > $logs/pl1_${r}_diag.log 2>&1
done
echo "all done $(date -u +%H:%M:%S)"
