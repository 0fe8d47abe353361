"""Step cost of positions in the slot decoder's cross-attention values (``dec_value_pos``),
priced on trained weights.

Encoder-side changes look cheap at initialisation, where every slot's field runs at every
point (the capacity probe beside this folder); trained, keep-mass selection drops most
slots per point. So each model starts here from its own 25,000-step run (its moving
average): the recipe's regression run and the ``dec_value_pos`` run, both seed 0. One
training step of each in turn (interleaved), 2 threads, the recipe's batch (4 scenes x
128 rays): the images are the first four training scenes' input views, so the slots are
real; the rays and targets are ``speedbench.make_batch``'s (into the scene box from a
camera-like distance). The committed JSON came from, at the repository root, alone:
    .venv/bin/python results/cpu/probe-value-pos/time_value_pos.py RECIPE_RUN VPOS_RUN 21 \
        DATA0/cpu/clevr567/train > results/cpu/probe-value-pos/time_value_pos.json
"""

import json
import sys
from pathlib import Path

import numpy as np
import torch
from PIL import Image

from benchmark.tools.speedbench import compare_train_steps, make_batch
from svorf.checkpoint import load_run

torch.set_num_threads(2)
if len(sys.argv) != 5:
    sys.exit("usage: time_value_pos.py RECIPE_RUN VPOS_RUN REPEATS TRAIN_SPLIT_DIR")
recipe_run, vpos_run, train_dir = sys.argv[1], sys.argv[2], Path(sys.argv[4])
repeats = int(sys.argv[3])
models = {}
for name, run in (("recipe", recipe_run), ("dec_value_pos", vpos_run)):
    m, info = load_run(run)
    m.train()
    m.set_progress(0.9)
    models[name] = m
mcfg = models["recipe"].cfg
views = sorted(train_dir.glob("*_az00.png"))[:4]
images = torch.tensor(
    np.stack([np.asarray(Image.open(p).convert("RGB"), dtype=np.float32) / 255.0 for p in views])
).permute(0, 3, 1, 2)
_, o, d, rgb = make_batch(mcfg, 4, 128)
report = compare_train_steps(models, (images, o, d, rgb), repeats=repeats)
report["runs"] = {"recipe": recipe_run, "dec_value_pos": vpos_run}
print(json.dumps(report, indent=1))
