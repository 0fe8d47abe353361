"""How many objects a model's slots find per scene, and how many slots it uses.

Usage: python slot_use.py OUT_JSON RUN[+masked] TEST [RUN[+masked] TEST ...]. For each
(run, test split) pair the input view of every test scene is rendered from the encoder's
slots (``render_input_view``, the benchmark's own labels); each ground-truth object is
sorted into own / merged / lost (``object_failures``), the slots other than the
background that are the argmax of at least 4 pixels are counted, and FG-ARI / ARI are
scored. ``RUN+masked`` renders with the run's training slot mask (``slot_mask_train``
random object slots off, drawn per scene from a fixed seed) instead of all slots. A
diagnosis, not a model.
"""

import json
import sys

import numpy as np
import torch

from benchmark.metrics.segmentation import ari_score, fg_ari_score
from benchmark.tools.failures import object_failures, render_input_view
from svorf.data import MultiViewDataset
from svorf.train import load_run

torch.set_num_threads(2)
out = {}


def render_masked(model, ds, i):
    """Labels [H, W] of scene i's input view with the training slot mask."""
    sv = ds[i]
    h, w = ds.image_hw
    mask = model.sample_slot_mask(1, generator=torch.Generator().manual_seed(i))
    with torch.no_grad():
        slots, extra = model.encode_for_render(sv.images[:1])
        rays = sv.rays_o[0].reshape(1, h * w, 3), sv.rays_d[0].reshape(1, h * w, 3)
        out = model.render_chunked(
            slots, *rays, 4096, input_c2w=sv.cam_to_world[:1], slot_mask=mask, **extra
        )
    return out.slot_probs[0].argmax(-1).view(h, w)


for arg, split in zip(sys.argv[2::2], sys.argv[3::2]):
    run, masked = arg.removesuffix("+masked"), arg.endswith("+masked")
    model, _ = load_run(run)
    model.eval()
    ds = MultiViewDataset(split, image_size=model.cfg.image_size)
    bg = model.cfg.num_slots - 1
    rows = []
    for i in range(len(ds)):
        labels = render_masked(model, ds, i) if masked else render_input_view(model, ds, i, i, 0)[0]
        gt = ds[i].instances[0]
        kinds = [r["kind"] for r in object_failures(labels, gt, bg)]
        ids, counts = labels.unique(return_counts=True)
        used = sum(1 for s, c in zip(ids.tolist(), counts.tolist()) if s != bg and c >= 4)
        rows.append(
            {
                "objects": len(kinds),
                "slots_used": used,
                "fg_ari": 100 * float(fg_ari_score(labels.reshape(1, -1), gt.reshape(1, -1))[0]),
                "ari": 100 * float(ari_score(labels.reshape(1, -1), gt.reshape(1, -1))[0]),
                **{k: kinds.count(k) for k in ("own", "merged", "lost")},
            }
        )
    key = f"{arg} on {split}"
    out[key] = {k: float(np.mean([r[k] for r in rows])) for k in rows[0]}
    out[key]["num_slots"] = model.cfg.num_slots
    out[key]["scenes_by_slots_used"] = np.bincount([r["slots_used"] for r in rows]).tolist()
    print(key, out[key], flush=True)
with open(sys.argv[1], "w") as f:
    json.dump(out, f, indent=1)
