#!/usr/bin/env bash
# Second pair of the fg_mass fine-tune probe: lambda 0.001 and 0.006, same conditions as probe_fgm.sh.
set -u
cd /work/main
src=/work/runs/abl/runs/fb2c15e3bf72d554
common="train-eval --data data/cpu/clevr567/train --test data/cpu/clevr567/test --minutes 10 --init-from $src --threads 1 --eval-every 0 --grid-scenes 6 --model-set slot_locality=0.6 --model-set slot_locality_narrow=null"
echo "start $(date -u +%H:%M:%S)"
.venv/bin/python -m benchmark.tools.recipe $common --out /work/runs/ft_fgm001 --model-set 'fg_mass=[0.001,0.0,0.2]' > /work/logs/ft_fgm001.log 2>&1 &
.venv/bin/python -m benchmark.tools.recipe $common --out /work/runs/ft_fgm006 --model-set 'fg_mass=[0.006,0.0,0.2]' > /work/logs/ft_fgm006.log 2>&1 &
wait
echo "done $(date -u +%H:%M:%S)"
