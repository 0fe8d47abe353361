#!/usr/bin/env bash
# Fine-tune probe: iterative inference inside training (TrainConfig.refine_train). The
# 12,500-step controls trained MIN more minutes, each step's slots refined 5 Adam steps
# (lr 2e-2) on 128 random pixels of each scene's input view before the target rays are
# rendered from them; ARM=ctl runs the same without the field. Seeds 0 and 1 side by side,
# 1 thread each (ARM=rt MIN=8; the control at about the same step count: ARM=ctl MIN=3.55
# TAG=ctl1k). Then each arm is scored with and without test-time refinement:
#   python -m benchmark.tools.refine RUN --test TEST --scenes 50 --steps 50
set -u
cd /work/main
PY=/work/main/.venv/bin/python
ARM=${ARM:-rt}; MIN=${MIN:-8}; TAG=${TAG:-$ARM}
echo "start $(date -u +%H:%M:%S)"
for seed in 0 1; do
  if [ $seed = 0 ]; then src=/work/runs/ctl_s0/runs/d0154b1382db5c06; data=/work/data0
  else src=/work/runs/ctl_s1/runs/d948a8155cd8e562; data=/work/data1; fi
  extra=()
  [ "$ARM" = rt ] && extra=(--train-set "refine_train=[5, 0.02, 128]")
  $PY -m benchmark.tools.recipe train-eval --data $data/cpu/clevr567/train --test $data/cpu/clevr567/test --minutes $MIN --init-from $src --threads 1 --eval-every 0 --grid-scenes 6 --seed $seed --lr 4e-4 "${extra[@]}" --out /work/runs/p${TAG}_s${seed} > /work/logs/p${TAG}_s${seed}.log 2>&1 &
done
wait
echo "trained $(date -u +%H:%M:%S)"
for seed in 0 1; do
  if [ $seed = 0 ]; then data=/work/data0; else data=/work/data1; fi
  $PY -m benchmark.tools.refine /work/runs/p${TAG}_s${seed} --test $data/cpu/clevr567/test --scenes 50 --steps 50 --threads 1 > /work/logs/p${TAG}_s${seed}.refine.log 2>&1 &
done
wait
echo "all done $(date -u +%H:%M:%S)"
