"""Held-out scores of a trained model rendered as trained and with the sampling box changed.

Usage: python probe.py RUN TEST THREADS [ARM,ARM,...]  (arms: as_trained, box_off,
floor_front; default as_trained,box_off). Prints one line per arm, then one JSON line.
A probe, not a model: the weights stay as trained, only where a ray's samples lie changes.
"""

import json
import sys

import torch

from benchmark import adapter
from benchmark.evaluate import aggregate, score_scene
from svorf.checkpoint import render_probe

ARMS = {
    "as_trained": {},
    "box_off": {
        "clip_to_box": False,
        "box_z": None,
        "clip_floor_z": None,
        "clip_floor_front": False,
    },
    "floor_front": {"clip_floor_front": True},
}
KEYS = ("psnr", "ssim", "fg_ari", "ari", "nv_ari", "depth_abs_rel")


def main() -> None:
    run, test = sys.argv[1], sys.argv[2]
    torch.set_num_threads(int(sys.argv[3]))
    arms = sys.argv[4].split(",") if len(sys.argv) > 4 else ["as_trained", "box_off"]
    out: dict = {}
    for name in arms:
        model = adapter.load_model(run)
        render_probe(model, ARMS[name])
        ds = adapter.open_dataset(test, image_size=model.cfg.image_size)
        acc: dict = {}
        for i in range(len(ds)):
            pred = adapter.predict_scene(model, ds, i)
            score_scene(
                pred_rgb=pred.rgb,
                pred_depth=pred.depth_z,
                pred_labels=pred.labels,
                truth=adapter.ground_truth(ds, i),
                input_view=0,
                with_lpips=False,
            ).append_to(acc)
        agg = aggregate(acc)[0]
        out[name] = {k: agg.get(k) for k in KEYS if k in agg}
        out[name]["n_scenes"] = len(ds)
        print(name, out[name], flush=True)
    print(json.dumps({"run": run, "test": test, **out}))


if __name__ == "__main__":
    main()
