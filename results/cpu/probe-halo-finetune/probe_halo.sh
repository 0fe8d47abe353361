#!/usr/bin/env bash
# Fine-tune probe of fg_mass_halo: the segmentation table's CLEVR-567 model (seed 0, 19,839 steps)
# trained 10 more minutes side by side (1 thread each), with and without the halo price;
# radius fixed at its end value.
set -u
cd /work/main
src=${SRC:-/work/runs/seg/runs/1b115338ae63f710}
common="train-eval --data data/cpu/clevr567/train --test data/cpu/clevr567/test --minutes ${MIN:-10} --init-from $src --threads 1 --eval-every 0 --grid-scenes 6 --model-set slot_locality=0.6 --model-set slot_locality_narrow=null"
echo "start $(date -u +%H:%M:%S)"
.venv/bin/python -m benchmark.tools.recipe $common --out /work/runs/fh_${A:-ctrl} ${ARGA:-} > /work/logs/fh_${A:-ctrl}.log 2>&1 &
.venv/bin/python -m benchmark.tools.recipe $common --out /work/runs/fh_${B:-halo} ${ARGB:---model-set fg_mass=[0.01,0.0,0.0] --model-set fg_mass_halo=0.1} > /work/logs/fh_${B:-halo}.log 2>&1 &
wait
echo "done $(date -u +%H:%M:%S)"
