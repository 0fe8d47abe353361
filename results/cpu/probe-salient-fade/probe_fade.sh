#!/usr/bin/env bash
# Fine-tune probe of uniform rays late in the run (TrainConfig.salient_fade): the recipe's
# 60-minute models (photo_l1 included; seed 0: 25,180 steps, seed 1: 25,272 steps, each on
# its own scenes) trained 10 more minutes, two arms side by side (1 thread each), with the
# recipe's object-heavy rays and with uniform rays (the salient share at 0) from the first
# step; the locality radius fixed at its end value (0.5) and the absolute photometric error
# on from the first step in both arms (the state the recipe ends in). Then `diagnose`.
set -u
cd "$(dirname "$0")/../../.."  # the repository root
runs=${RUNS:-/work/runs}; logs=${LOGS:-/work/logs}
for seed in 0 1; do
  if [ $seed = 0 ]; then
    src=${SRC0:-$runs/l1_s0/runs/6ffc2ae90e183614}; data=${DATA0:-/work/wt_l1/data}
  else
    src=${SRC1:-$runs/l1_s1/runs/79fb7674bbce8029}; data=${DATA1:-data}
  fi
  common="train-eval --data $data/cpu/clevr567/train --test $data/cpu/clevr567/test --minutes ${MIN:-10} --init-from $src --threads 1 --eval-every 0 --grid-scenes 6 --seed $seed --model-set slot_locality=0.5 --model-set slot_locality_narrow=null --model-set photo_l1=[0.0,0.0]"
  echo "seed $seed start $(date -u +%H:%M:%S)"
  .venv/bin/python -m benchmark.tools.recipe $common --out $runs/sf_s${seed}_ctrl > $logs/sf_s${seed}_ctrl.log 2>&1 &
  .venv/bin/python -m benchmark.tools.recipe $common --out $runs/sf_s${seed}_unif --ray-sampling uniform > $logs/sf_s${seed}_unif.log 2>&1 &
  wait
  echo "seed $seed done $(date -u +%H:%M:%S)"
done
for seed in 0 1; do
  data=$([ $seed = 0 ] && echo ${DATA0:-/work/wt_l1/data} || echo ${DATA1:-data})
  for arm in ctrl unif; do
    .venv/bin/python -m benchmark.tools.recipe diagnose $runs/sf_s${seed}_$arm --test $data/cpu/clevr567/test > $logs/sf_s${seed}_${arm}_diag.log 2>&1
  done
done
echo "all done $(date -u +%H:%M:%S)"
