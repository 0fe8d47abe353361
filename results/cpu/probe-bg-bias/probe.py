"""Held-out segmentation of a trained model with the background slot's share of each pixel
scaled by a factor b before the arg-max (b = 1: the benchmark's own labels).

Usage: python probe.py RUN TEST OUT_JSON [SCENES] [THREADS]. Renders every view of each test
scene once (``svorf.predict.predict_scene``, input view 0, the encoder's slots) and scores
the labels ``argmax(p with p[background] * b)`` for each b with the benchmark's
``segmentation_metrics``. A readout probe, not a model: colour, depth and the weights are
unchanged; only which slot wins a pixel where object and background share it moves.
"""

import json
import sys
from pathlib import Path

import torch

from benchmark.metrics.segmentation import segmentation_metrics
from svorf.data import MultiViewDataset
from svorf.predict import predict_scene
from svorf.train import load_run

FACTORS = [0.8, 1.0, 1.1, 1.25, 1.5, 1.75, 2.0, 2.5, 3.0, 4.0]

run, split, out = Path(sys.argv[1]), sys.argv[2], sys.argv[3]
n = int(sys.argv[4]) if len(sys.argv) > 4 else None
torch.set_num_threads(int(sys.argv[5]) if len(sys.argv) > 5 else 1)
model, info = load_run(run)
ds = MultiViewDataset(split, image_size=model.cfg.image_size, max_scenes=n)
bg = model.cfg.num_slots - 1
acc = {b: {"ari": [], "fg_ari": [], "nv_ari": []} for b in FACTORS}
for i in range(len(ds)):
    p = predict_scene(model, ds, i)
    gt = ds[i].instances  # [V, H, W]
    for b in FACTORS:
        q = p.slot_probs.clone()
        q[..., bg] *= b
        m = segmentation_metrics(q.argmax(-1)[None], gt[None].long())
        for k in acc[b]:
            acc[b][k].append(float(m[k][0]))
res = {"step": info.step, "n": len(ds), "rows": {}}
for b in FACTORS:
    res["rows"][str(b)] = {k: 100 * float(torch.tensor(v).nanmean()) for k, v in acc[b].items()}
    print(b, {k: round(x, 2) for k, x in res["rows"][str(b)].items()}, flush=True)
Path(out).write_text(json.dumps(res, indent=1))
