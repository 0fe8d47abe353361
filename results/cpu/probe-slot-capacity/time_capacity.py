"""Step cost of more slot-inference capacity on the cpu recipe's model.

Candidates against the encoder's amortisation gap (test-time slot refinement lifts ARI
about 5 points, so the encoder's single pass is what limits the rim): a deeper slot
decoder (``dec_layers`` 3 -> 4), a wider decoder feed-forward (``dec_ffn`` 256 -> 512), a
deeper encoder (``enc_blocks`` (1, 1, 1) -> (2, 2, 2)) and a wider one (``enc_width`` 32 ->
48). One training step of each model in turn (interleaved), 2 threads, the recipe's
batch (4 scenes x 128 rays, random images and rays from ``speedbench.make_batch``),
progress 0.9. At initialisation every slot's field runs at every point, so this
under-prices encoder changes: the deeper encoder and decoder timed 1.09x here cost 1.34x a
step in training. The committed JSON came from, at the repository root, alone:
    .venv/bin/python results/cpu/probe-slot-capacity/time_capacity.py 21 > results/cpu/probe-slot-capacity/time_capacity.json
"""

import json
import sys

import torch

from benchmark.tools.speedbench import compare_train_steps, make_batch
from svorf.model import SVORF
from svorf.train import run_configs

VARIANTS = {
    "recipe": {},
    "dec_layers=4": {"dec_layers": 4},
    "dec_ffn=512": {"dec_ffn": 512},
    "enc_blocks=(2,2,2)": {"enc_blocks": (2, 2, 2)},
    "enc_width=48": {"enc_width": 48},
}

torch.set_num_threads(2)
mcfg, tcfg = run_configs("cpu", "clevr567")
models = {}
for name, over in VARIANTS.items():
    torch.manual_seed(0)
    m = SVORF(mcfg.replace(**over)).train()
    m.set_progress(0.9)
    models[name] = m
batch = make_batch(mcfg, tcfg.batch_scenes, tcfg.rays_per_scene)
repeats = int(sys.argv[1]) if len(sys.argv) > 1 else 15
params = {n: sum(p.numel() for p in m.parameters()) for n, m in models.items()}
report = compare_train_steps(models, batch, repeats=repeats)
print(json.dumps({**report, "params": params}, indent=1))
