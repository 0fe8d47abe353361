"""Step cost of wider object fields (``ModelConfig.mlp_width``) on the cpu recipe's model.

One training step of each model in turn (interleaved), 2 threads, the recipe's batch
(4 scenes x 128 rays, random images and rays from ``speedbench.make_batch``), progress 0.9.
Run from the repository root, alone on the machine:
    .venv/bin/python results/cpu/probe-mlp-width/time_mlp_width.py 31 > results/cpu/probe-mlp-width/time_mlp_width.json
"""

import json
import sys

import torch

from benchmark.tools.speedbench import compare_train_steps, make_batch
from svorf.model import SVORF
from svorf.train import run_configs

WIDTHS = (64, 96, 128)

torch.set_num_threads(2)
mcfg, tcfg = run_configs("cpu", "clevr567")
models = {}
for w in WIDTHS:
    torch.manual_seed(0)
    m = SVORF(mcfg.replace(mlp_width=w)).train()
    m.set_progress(0.9)
    models[f"mlp_width={w}"] = m
batch = make_batch(mcfg, tcfg.batch_scenes, tcfg.rays_per_scene)
repeats = int(sys.argv[1]) if len(sys.argv) > 1 else 15
params = {n: sum(p.numel() for p in m.parameters()) for n, m in models.items()}
report = compare_train_steps(models, batch, repeats=repeats)
print(json.dumps({**report, "params": params}, indent=1))
