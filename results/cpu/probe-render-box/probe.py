# scratch: held-out scores of a trained model rendered as trained and with the sampling box off
# usage: boxoff.py RUN TEST THREADS
import sys, json
import torch
torch.set_num_threads(int(sys.argv[3]))
from benchmark import adapter
from benchmark.evaluate import score_scene, aggregate
from svorf.checkpoint import render_probe
run, test = sys.argv[1], sys.argv[2]
out = {}
ARMS = {"as_trained": {}, "box_off": {"clip_to_box": False, "box_z": None, "clip_floor_z": None, "clip_floor_front": False}, "floor_front": {"clip_floor_front": True}}
for name in (sys.argv[4].split(",") if len(sys.argv) > 4 else ["as_trained", "box_off"]):
    probe = ARMS[name]
    model = adapter.load_model(run)
    render_probe(model, probe)
    ds = adapter.open_dataset(test, image_size=model.cfg.image_size)
    acc = {}
    for i in range(len(ds)):
        pred = adapter.predict_scene(model, ds, i)
        score_scene(pred_rgb=pred.rgb, pred_depth=pred.depth_z, pred_labels=pred.labels,
                    truth=adapter.ground_truth(ds, i), input_view=0, with_lpips=False).append_to(acc)
    agg = aggregate(acc)[0]
    out[name] = {k: agg.get(k) for k in ("psnr", "ssim", "fg_ari", "ari", "nv_ari", "depth_abs_rel") if k in agg}
    out[name]["n_scenes"] = len(ds)
    print(name, out[name], flush=True)
print(json.dumps({"run": run, "test": test, **out}))
