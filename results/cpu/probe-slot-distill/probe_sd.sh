#!/usr/bin/env bash
# Fine-tune probe: slot distillation (TrainConfig.slot_distill). The 12,500-step controls
# trained 8 more minutes with the encoder's slots pulled towards 5 Adam steps (lr 2e-2) of
# refinement on each step's own rays, weight W; seeds 0 and 1 side by side, 1 thread each.
set -u
cd /work/wt_sd
PY=/work/main/.venv/bin/python
W=${W:-1.0}; TAG=${TAG:-sd}
echo "start $(date -u +%H:%M:%S)"
for seed in 0 1; do
  if [ $seed = 0 ]; then src=/work/runs/ctl_s0/runs/d0154b1382db5c06; data=/work/data0
  else src=/work/runs/ctl_s1/runs/d948a8155cd8e562; data=/work/data1; fi
  $PY -m benchmark.tools.recipe train-eval --data $data/cpu/clevr567/train --test $data/cpu/clevr567/test --minutes ${MIN:-8} --init-from $src --threads 1 --eval-every 0 --grid-scenes 6 --seed $seed --lr 4e-4 --train-set "slot_distill=[$W, 5, 0.02]" --out /work/runs/p${TAG}_s${seed} > /work/logs/p${TAG}_s${seed}.log 2>&1 &
done
wait
echo "all done $(date -u +%H:%M:%S)"
