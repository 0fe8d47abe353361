"""Which objects an RGB-trained model loses on grayscale test images, and why.

Usage: python probe.py RUN RGB_TEST GRAY_TEST OUT_JSON [THREADS]. GRAY_TEST holds the same
scenes as RGB_TEST in Rec.601 luma (``generate``'s clevr567-gray preset). For each scene the
input view is rendered from the encoder's slots twice, once from the RGB image and once from
the gray one (``benchmark.tools.failures.render_input_view``, the benchmark's own labels),
and every ground-truth object is sorted into lost / merged / own by
``benchmark.tools.failures.object_failures`` under both. Each object also gets its contrast
against the floor around it (a 2-pixel ring outside its mask, other objects excluded): the
mean absolute difference of its pixels' luma from the ring's (what the gray image keeps)
and of their RGB colour (what the RGB image has). A diagnosis, not a model.
"""

import itertools
import json
import sys
from collections import defaultdict
from pathlib import Path

import numpy as np
import torch

from benchmark.tools.failures import object_failures, render_input_view
from benchmark.tools.rim import dilate
from scenefmt import LUMA_REC601
from svorf.data import MultiViewDataset
from svorf.train import load_run

LUMA = torch.tensor(LUMA_REC601)

run, rgb_split, gray_split, out = Path(sys.argv[1]), sys.argv[2], sys.argv[3], sys.argv[4]
torch.set_num_threads(int(sys.argv[5]) if len(sys.argv) > 5 else 2)
model, info = load_run(run)
rgb_ds = MultiViewDataset(rgb_split, image_size=model.cfg.image_size)
gray_ds = MultiViewDataset(gray_split, image_size=model.cfg.image_size)
if len(rgb_ds) != len(gray_ds):
    sys.exit(f"probe.py: {rgb_split} has {len(rgb_ds)} scenes, {gray_split} {len(gray_ds)}")
bg = model.cfg.num_slots - 1
objects = []
for i in range(len(rgb_ds)):
    sv = rgb_ds[i]
    gt = sv.instances[0]
    image = sv.images[0].permute(1, 2, 0)  # [H, W, 3] in [0, 1]
    luma = image @ LUMA
    scene = json.loads((Path(rgb_split) / f"sc{rgb_ds.scene_ids[i]:04d}.json").read_text())
    kinds = {}
    for name, ds in (("rgb", rgb_ds), ("gray", gray_ds)):
        labels, _ = render_input_view(model, ds, i, i, 0)
        kinds[name] = {r["id"]: r for r in object_failures(labels, gt, bg)}
    for oid, r in kinds["rgb"].items():
        inside = gt == oid
        ring = dilate(inside, 2) & (gt == 0)
        if not ring.any():
            continue
        o = scene["objects"][oid - 1]
        objects.append(
            {
                "scene": i,
                "id": oid,
                "pixels": r["pixels"],
                "color": o["color"],
                "material": o["material"],
                "shape": o["shape"],
                "size": o["size_name"],
                "rgb": r["kind"],
                "gray": kinds["gray"][oid]["kind"],
                "luma_contrast": float((luma[inside].mean() - luma[ring].mean()).abs()),
                "rgb_contrast": float((image[inside].mean(0) - image[ring].mean(0)).abs().mean()),
            }
        )


def table(key):
    rows = defaultdict(list)
    for o in objects:
        rows[key(o)].append(o)
    return {
        str(k): {
            "objects": len(v),
            "lost_rgb": float(np.mean([o["rgb"] == "lost" for o in v])),
            "lost_gray": float(np.mean([o["gray"] == "lost" for o in v])),
            "merged_rgb": float(np.mean([o["rgb"] == "merged" for o in v])),
            "merged_gray": float(np.mean([o["gray"] == "merged" for o in v])),
            "luma_contrast": float(np.mean([o["luma_contrast"] for o in v])),
        }
        for k, v in sorted(rows.items())
    }


edges = [0.0, 0.05, 0.1, 0.2, 1.01]


def contrast_bin(o):
    for lo, hi in itertools.pairwise(edges):
        if lo <= o["luma_contrast"] < hi:
            return f"{lo:.2f}-{hi:.2f}"


def pixel_bin(o):
    return "<=20 px" if o["pixels"] <= 20 else ("21-60 px" if o["pixels"] <= 60 else ">60 px")


res = {
    "run": str(run),
    "step": info.step,
    "scenes": len(rgb_ds),
    "objects": len(objects),
    "by_luma_contrast": table(contrast_bin),
    "by_color": table(lambda o: o["color"]),
    "by_size_in_view": table(pixel_bin),
    "by_material": table(lambda o: o["material"]),
    "transitions": {
        f"{a}->{b}": sum(o["rgb"] == a and o["gray"] == b for o in objects)
        for a in ("own", "merged", "lost")
        for b in ("own", "merged", "lost")
    },
    "per_object": objects,
}
Path(out).write_text(json.dumps(res, indent=1))
for k in ("by_luma_contrast", "by_color", "by_size_in_view", "by_material"):
    print(k)
    for name, r in res[k].items():
        print(
            f"  {name:>12}: n={r['objects']:3d} lost rgb {100 * r['lost_rgb']:5.1f}% gray "
            f"{100 * r['lost_gray']:5.1f}%  merged rgb {100 * r['merged_rgb']:4.1f}% gray "
            f"{100 * r['merged_gray']:4.1f}%  luma contrast {r['luma_contrast']:.3f}"
        )
print("transitions", res["transitions"])
