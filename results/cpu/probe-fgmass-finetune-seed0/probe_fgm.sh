#!/usr/bin/env bash
# Fine-tune probe of fg_mass: the ablation's full model (seed 0, 20,528 steps) trained 10 more
# minutes side by side (1 thread each), with and without the price; radius fixed at its end value.
set -u
cd /work/main
src=/work/runs/abl/runs/fb2c15e3bf72d554
common="train-eval --data data/cpu/clevr567/train --test data/cpu/clevr567/test --minutes ${MIN:-10} --init-from $src --threads 1 --eval-every 0 --grid-scenes 6 --model-set slot_locality=0.6 --model-set slot_locality_narrow=null"
echo "start $(date -u +%H:%M:%S)"
.venv/bin/python -m benchmark.tools.recipe $common --out /work/runs/ft_ctrl > /work/logs/ft_ctrl.log 2>&1 &
.venv/bin/python -m benchmark.tools.recipe $common --out /work/runs/ft_fgm --model-set 'fg_mass=[0.003,0.0,0.2]' > /work/logs/ft_fgm.log 2>&1 &
wait
echo "done $(date -u +%H:%M:%S)"
