"""CPU-scale training recipe for sVORF: time-budgeted training with held-out
segmentation metrics over wall-clock time, and the recipe's levers as config fields.

Where it sits: a tool of the benchmark's tools package, on top of ``svorf.train.train``
(which it calls with ``max_wall_s`` and an ``eval_fn``); it imports only ``svorf`` and
``scenefmt`` (and, for ``diagnose --occlusion``, ``benchmark.tools.occlusion``, which
ray-casts the scene JSONs with ``generators``). The segmentation metrics are a callable
(:func:`make_eval_fn`), by default the ARI, FG-ARI and NV-ARI of this module
(:func:`segmentation_metrics_basic`, from ``svorf.ari``, the project's one ARI that the
benchmark scores with too; equal to ``benchmark.metrics.segmentation_metrics`` on those
keys: tests/test_recipe.py), which the command line (``python -m benchmark.tools.recipe
train-eval``) uses too.

The levers (every one a documented config field that the paper scale leaves off):

==================  ===========================================  =========================
lever               field                                        paper value
==================  ===========================================  =========================
object-heavy rays   ``TrainConfig.ray_sampling="object_heavy"``  "uniform"
error-driven rays   ``ray_sampling="error_driven"`` (ErrorMap)   "uniform" (lever row)
input-view warm-up  ``TrainConfig.nvs_warmup``                   0
learning rate       ``TrainConfig.lr`` / ``warmup``              1e-4 / 1000
batch shape         ``TrainConfig.batch_scenes`` / ``rays_...``  16 / 64
floor -> background ``ModelConfig.fg_zmin``                      None
locality box        ``ModelConfig.fg_box``                       None
bg outside objects  ``ModelConfig.bg_outside_fg``                False
comp. temperature   ``ModelConfig.comp_temperature``             1.0
slot locality       ``ModelConfig.slot_locality``                None
centre source       ``ModelConfig.slot_centre`` ("anchored")     "learned" (unused)
bg bandwidth        ``ModelConfig.bg_pos_freqs_xyz``             None (lever row)
==================  ===========================================  =========================

``ModelConfig.coord_frame="input_azimuth"`` (the networks see the input camera's azimuth
frame) is not a recipe lever: it is the default at every scale (uORF's convention); the
recipe runs compare it with ``"world"`` (``--coord-frame``).

Measurements and the recommended command are in docs/notes/cpu_recipe.md.
"""

from __future__ import annotations

import json
import math
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor

from benchmark.tools.failures import depth_breakdown, failure_breakdown, render_input_view
from scenefmt import atomic_write_json
from scenefmt.cli_util import USAGE, OneLineParser, doc_summary, fail
from svorf.ari import adjusted_rand_index
from svorf.checkpoint import WEIGHTS, CheckpointError, render_probe
from svorf.config import ModelConfig
from svorf.data import MultiViewDataset
from svorf.model import SVORF
from svorf.train import (
    CPU_RECIPE,
    CPU_RECIPE_MODEL_FIELDS,
    TrainConfig,
    apply_recipe,
    load_run,
    predict_scene,
    run_configs,
    train,
)

__all__ = [
    "RECIPE_LEVERS",
    "SegMetricsFn",
    "adjusted_rand_index",
    "make_eval_fn",
    "plot_runs",
    "recipe_configs",
    "recipe_model_levers",
    "save_segmentation_grid",
    "segmentation_metrics_basic",
    "train_eval",
]

#: ``fn(pred [B, V, H, W], gt [B, V, H, W], input_view) -> {name: [B] tensor}`` with at
#: least ``ari``, ``fg_ari``, ``nv_ari`` (the signature of
#: ``benchmark.metrics.segmentation_metrics``).
SegMetricsFn = Callable[[Tensor, Tensor, int], dict[str, Tensor]]

#: The recipe's choices on top of the plain cpu scale (docs/notes/cpu_recipe.md): train fields
#: and model fields. It lives in svorf's scale registry (``svorf.registry.SCALES["cpu"].recipe``,
#: also ``svorf.train.CPU_RECIPE``), so ``svorf train --scale cpu`` and ``benchmark --scale
#: cpu`` train the same model; ``recipe_configs(levers=...)`` overrides entries.
RECIPE_LEVERS: dict[str, Any] = CPU_RECIPE

_MODEL_LEVERS = CPU_RECIPE_MODEL_FIELDS


def recipe_model_levers(levers: dict[str, Any] | None = None) -> dict[str, Any]:
    """The ModelConfig fields :data:`RECIPE_LEVERS` (with ``levers`` replacing entries) sets."""
    lv = {**RECIPE_LEVERS, **(levers or {})}
    return {k: lv[k] for k in _MODEL_LEVERS if k in lv}


def recipe_configs(
    preset: str = "clevr567", levers: dict[str, Any] | None = None, **train_overrides: Any
) -> tuple[ModelConfig, TrainConfig]:
    """(model, train) configs of the cpu recipe: cpu scale + :data:`RECIPE_LEVERS`.

    ``levers`` replaces or adds entries of :data:`RECIPE_LEVERS` (a ModelConfig field goes
    to the model, anything else to the TrainConfig); ``train_overrides`` are
    further TrainConfig fields (steps, lr, batch_scenes, ...). With no levers this equals
    ``svorf.train.run_configs("cpu", preset)`` for the recipe's presets.
    """
    mcfg, tcfg = run_configs("cpu", preset, recipe=False)
    mcfg, tcfg = apply_recipe(mcfg, tcfg, levers, preset=preset)
    return mcfg, tcfg.replace(**train_overrides)


# --------------------------------------------------------------------------- metrics


def segmentation_metrics_basic(pred: Tensor, gt: Tensor, input_view: int = 0) -> dict[str, Tensor]:
    """A small stand-in for ``benchmark.metrics.segmentation_metrics``: ``ari``,
    ``fg_ari`` (input view) and ``nv_ari`` (mean over the other views), each [B]."""
    out: dict[str, list[float]] = {"ari": [], "fg_ari": [], "nv_ari": []}
    for b in range(pred.shape[0]):
        out["ari"].append(adjusted_rand_index(pred[b, input_view], gt[b, input_view]))
        out["fg_ari"].append(
            adjusted_rand_index(pred[b, input_view], gt[b, input_view], gt[b, input_view] > 0)
        )
        nv = [adjusted_rand_index(pred[b, v], gt[b, v])
              for v in range(pred.shape[1]) if v != input_view]  # fmt: skip
        out["nv_ari"].append(float(np.mean(nv)) if nv else math.nan)
    return {k: torch.tensor(v, dtype=torch.float64) for k, v in out.items()}


def make_eval_fn(
    seg_metrics: SegMetricsFn | None = None, max_scenes: int = 8, input_view: int = 0
) -> Callable[[SVORF, MultiViewDataset], dict[str, float]]:
    """An ``eval_fn`` for :func:`svorf.train.train`: held-out segmentation and PSNR.

    Renders every view of the first ``max_scenes`` scenes from ``input_view`` and returns
    the scene means of ``seg_metrics`` (default :func:`segmentation_metrics_basic`) plus
    ``psnr_input`` / ``psnr_novel`` (PSNR of the mean MSE) and ``n_scenes``.

    It also returns ``fg_ari_shuffled``: the FG-ARI of the input view when scene i is
    rendered with the slots of scene i+1 (same relative camera): the score of a
    segmentation that does not look at the scene. A model that decomposes scores far above
    it; a model whose foreground slots tile space in a fixed pattern (a spatial prior, not
    decomposition) scores about the same (``fg_ari - fg_ari_shuffled`` is reported as
    ``fg_ari_gain``).
    """
    seg = seg_metrics or segmentation_metrics_basic

    def fn(model: SVORF, ds: MultiViewDataset) -> dict[str, float]:
        n = min(max_scenes, len(ds))
        preds, gts, mse_in, mse_nv = [], [], [], []
        for i in range(n):
            p = predict_scene(model, ds, i, input_view=input_view)
            sv = ds[i]
            preds.append(p.labels)
            gts.append(sv.instances)
            err = ((p.rgb - sv.images.permute(0, 2, 3, 1)) ** 2).mean(dim=(1, 2, 3))
            mse_in.append(float(err[input_view]))
            others = [float(e) for v, e in enumerate(err) if v != input_view]
            if others:
                mse_nv.append(float(np.mean(others)))
        m = seg(torch.stack(preds), torch.stack(gts), input_view)
        res = {k: float(np.nanmean(v.double().numpy())) for k, v in m.items()}
        if n >= 2:
            shuf = [_labels_with_slots_of(model, ds, i, (i + 1) % n, input_view) for i in range(n)]
            gt_in = torch.stack([g[input_view : input_view + 1] for g in gts])
            ms = seg(torch.stack(shuf)[:, None], gt_in, 0)
            res["fg_ari_shuffled"] = float(np.nanmean(ms["fg_ari"].double().numpy()))
            res["fg_ari_gain"] = res["fg_ari"] - res["fg_ari_shuffled"]

        def psnr(xs: list[float]) -> float:
            return -10.0 * math.log10(max(float(np.mean(xs)), 1e-10)) if xs else math.nan

        res.update(psnr_input=psnr(mse_in), psnr_novel=psnr(mse_nv), n_scenes=float(n))
        return res

    return fn


def _labels_with_slots_of(
    model: SVORF, ds: MultiViewDataset, scene: int, other: int, input_view: int
) -> Tensor:
    """[H, W] arg-max slot labels of ``scene``'s input view rendered from the slots of scene
    ``other`` (encoded from its own input view) placed in ``scene``'s input-camera frame."""
    return render_input_view(model, ds, scene, other, input_view)[0]


# --------------------------------------------------------------------------- figures


def save_segmentation_grid(
    model: SVORF, ds: MultiViewDataset, path: str | Path, n_scenes: int = 6, input_view: int = 0
) -> Path:
    """PNG: one row per held-out scene: input view, reconstruction, predicted slots (input
    view), ground-truth instances, then predicted slots / ground truth of the next view."""
    from PIL import Image

    from svorf.viz import colorize_labels, to_uint8

    rows = []
    for i in range(min(n_scenes, len(ds))):
        p = predict_scene(model, ds, i, input_view=input_view)
        sv = ds[i]
        nv = (input_view + 1) % ds.n_views
        tiles = [
            to_uint8(sv.images[input_view].permute(1, 2, 0)),
            to_uint8(p.rgb[input_view]),
            colorize_labels(p.labels[input_view], background=model.cfg.num_slots - 1),
            colorize_labels(sv.instances[input_view], background=0),
            to_uint8(p.rgb[nv]),
            colorize_labels(p.labels[nv], background=model.cfg.num_slots - 1),
            colorize_labels(sv.instances[nv], background=0),
        ]
        rows.append(np.concatenate([np.pad(t, ((1, 1), (1, 1), (0, 0))) for t in tiles], 1))
    img = np.concatenate(rows, 0)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(img).resize((img.shape[1] * 2, img.shape[0] * 2), Image.NEAREST).save(path)
    return path


# --------------------------------------------------------------------------- driver


def train_eval(
    data_dir: str | Path,
    test_dir: str | Path,
    out_dir: str | Path,
    minutes: float,
    model_cfg: ModelConfig,
    train_cfg: TrainConfig,
    *,
    seg_metrics: SegMetricsFn | None = None,
    resume: bool = False,
    grid_scenes: int = 6,
    final_scenes: int | None = None,
    train_scenes: int | None = None,
    progress: bool = False,
    init_from: str | Path | None = None,
) -> dict[str, Any]:
    """Train for ``minutes`` of training wall time (evaluations excluded), evaluating the
    held-out split every ``train_cfg.eval_every`` steps (eval.jsonl), then write
    ``grid.png`` and ``final_eval.json``. ``resume`` continues an interrupted run (the
    budget counts the time already trained). ``final_scenes``: test scenes of the final
    evaluation (None = every scene of ``test_dir``). ``init_from``: a run folder or
    checkpoint whose matching tensors start the run (``svorf.train.train``)."""
    out = Path(out_dir)
    eval_fn = make_eval_fn(seg_metrics, train_cfg.eval_scenes)
    summary = train(data_dir, out, model_cfg, train_cfg, resume=resume, eval_fn=eval_fn,
                    eval_data=test_dir, progress=progress, max_wall_s=minutes * 60.0,
                    max_scenes=train_scenes, init_from=init_from)  # fmt: skip
    model, info = load_run(out)
    test = MultiViewDataset(test_dir, image_size=model_cfg.image_size, max_scenes=final_scenes)
    with torch.no_grad():
        final = make_eval_fn(seg_metrics, len(test))(model, test)
    final.update(step=info.step, wall_s=info.wall_s)
    final["failures"] = failure_breakdown(model, test)
    atomic_write_json(out / "final_eval.json", final)
    save_segmentation_grid(model, test, out / "grid.png", grid_scenes)
    return {"summary": summary.to_dict(), "final": final, "grid": str(out / "grid.png")}


def _read_jsonl(path: Path) -> list[dict[str, Any]]:
    if not path.is_file():
        return []
    return [json.loads(line) for line in path.read_text().splitlines() if line.strip()]


def plot_runs(runs: dict[str, str | Path], path: str | Path) -> Path:
    """PNG of recipe runs side by side over training wall time (minutes): the training
    loss (``log.jsonl``) and the held-out FG-ARI with its scene-shuffle control
    (``eval.jsonl``: solid = FG-ARI, dashed = ``fg_ari_shuffled``).

    Args:
        runs: label -> run folder of :func:`train_eval`.
        path: output PNG.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax_l, ax_m) = plt.subplots(1, 2, figsize=(11, 4))
    for i, (label, run) in enumerate(runs.items()):
        colour = f"C{i}"
        log = _read_jsonl(Path(run) / "log.jsonl")
        if log:
            ax_l.plot([r["wall_s"] / 60 for r in log], [r["loss"] for r in log], colour,
                      lw=0.8, label=label)  # fmt: skip
        ev = _read_jsonl(Path(run) / "eval.jsonl")
        if ev:
            t = [r["wall_s"] / 60 for r in ev]
            ax_m.plot(t, [r["fg_ari"] for r in ev], colour, marker="o", label=f"{label}: FG-ARI")
            if all("fg_ari_shuffled" in r for r in ev):
                ax_m.plot(t, [r["fg_ari_shuffled"] for r in ev], colour, ls="--", marker="x",
                          label=f"{label}: shuffled slots")  # fmt: skip
    ax_l.set(xlabel="training wall time (min)", ylabel="training loss", yscale="log",
             title="loss")  # fmt: skip
    ax_m.set(xlabel="training wall time (min)", ylabel="held-out FG-ARI", ylim=(0, 1),
             title="held-out FG-ARI (input view)")  # fmt: skip
    ax_l.legend(fontsize=8)
    ax_m.legend(fontsize=7)
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


_PROG = "python -m benchmark.tools.recipe"


def main(argv: list[str] | None = None) -> int:
    """``python -m benchmark.tools.recipe train-eval|diagnose|plot``; returns the exit status (a bad
    command line prints one line ``python -m benchmark.tools.recipe: error: ...``, status 2)."""
    from svorf.train import CHECKPOINT_NAME, PRESETS

    ap = OneLineParser(
        prog=_PROG,
        description=doc_summary(__doc__),
        epilog="Measurements and the recommended command: docs/notes/cpu_recipe.md.",
    )
    sub = ap.add_subparsers(dest="cmd", required=True)
    t = sub.add_parser("train-eval", help="time-budgeted cpu-recipe training with held-out eval")
    t.add_argument("--data", required=True, help="training split folder")
    t.add_argument("--test", required=True, help="held-out split (with instance ids)")
    t.add_argument("--out", required=True, help="run folder")
    t.add_argument("--minutes", type=float, required=True, help="training wall-time budget")
    t.add_argument("--preset", default="clevr567", choices=sorted(PRESETS), help="training preset")
    t.add_argument("--resume", action="store_true", help="continue the run in --out")
    t.add_argument("--init-from", default=None, metavar="RUN",
                   help="start from this run's weights (a fine-tune probe; tensors that match)")  # fmt: skip
    t.add_argument("--threads", type=int, default=2, help="torch CPU threads")
    t.add_argument("--eval-every", type=int, default=150, help="held-out eval every N steps")
    t.add_argument("--eval-scenes", type=int, default=8, help="scenes of each held-out eval")
    t.add_argument("--grid-scenes", type=int, default=6, help="scenes in grid.png")
    t.add_argument("--final-scenes", type=int, default=None, help="default: all test scenes")
    t.add_argument("--train-scenes", type=int, default=None, help="default: all (overfit checks)")
    t.add_argument("--ray-sampling", default=None, help="lever (default: the recipe's)")
    t.add_argument("--nvs-warmup", type=int, default=None, help="lever (default: the recipe's)")
    t.add_argument("--fg-zmin", type=float, default=None, help="negative = off")
    t.add_argument("--fg-box", type=float, default=None, help="<= 0 = off")
    t.add_argument("--comp-temperature", type=float, default=None,
                   help="lever (default: the recipe's)")  # fmt: skip
    t.add_argument("--coord-frame", choices=("input_azimuth", "world"), default=None,
                   help="networks' frame (default: the scale's)")  # fmt: skip
    t.add_argument("--bg-outside-fg", type=int, default=None, help="1 = on, 0 = off")
    t.add_argument("--lr", type=float, default=None, help="default: the recipe's")
    t.add_argument("--warmup", type=int, default=None, help="default: the recipe's")
    t.add_argument("--batch-scenes", type=int, default=None, help="default: the recipe's")
    t.add_argument("--rays-per-scene", type=int, default=None, help="default: the recipe's")
    t.add_argument("--seed", type=int, default=None, help="default: 0")
    t.add_argument(
        "--model-set",
        action="append",
        default=[],
        metavar="FIELD=VALUE",
        help="any other ModelConfig field (VALUE as JSON, else a string), repeatable; "
        "e.g. --model-set slot_module=slot_attention",
    )
    t.add_argument(
        "--train-set",
        action="append",
        default=[],
        metavar="FIELD=VALUE",
        help="any other TrainConfig field (VALUE as JSON, else a string), repeatable; "
        "e.g. --train-set target_size=128",
    )
    dg = sub.add_parser(
        "diagnose",
        help="per-object failure breakdown of a run on held-out scenes (lost / merged / own)",
    )
    dg.add_argument("run", help="a recipe or svorf run folder (checkpoint.pt)")
    dg.add_argument("--test", required=True, help="held-out split with instance ids")
    dg.add_argument("--scenes", type=int, default=None, help="default: all test scenes")
    dg.add_argument("--threads", type=int, default=2, help="torch CPU threads")
    dg.add_argument("--grid", default=None, metavar="PNG",
                    help="also write a grid of held-out segmentations (the first --grid-scenes "
                    "test scenes; columns as train-eval's grid.png)")  # fmt: skip
    dg.add_argument("--grid-scenes", type=int, default=6, help="scenes in --grid (default: 6)")
    dg.add_argument("--depth", action="store_true",
                    help="also break the novel-view depth error down (objects, background "
                    "inside / outside the sampled box); renders every view, slower")  # fmt: skip
    dg.add_argument("--render-set", action="append", default=[], metavar="FIELD=VALUE",
                    help="render with another value of a scene prior (fg_zmin, fg_box, "
                    "bg_outside_fg), of the samples per ray (n_coarse, n_fine) and where they "
                    "are taken (clip_to_box, box_z, clip_floor_z, clip_floor_front) or of the "
                    "soft masks' temperature (comp_temperature) or how a pixel's masks are "
                    "read from its ray (eval_mask_rule=peak or peak_background), "
                    "repeatable: a probe of where the errors live, written to "
                    "failures-probe.json")  # fmt: skip
    dg.add_argument("--occlusion", action="store_true",
                    help="also break the failures down by how much of each object other "
                    "objects hide in the input view (ray-cast from the scene JSONs)")  # fmt: skip
    dg.add_argument("--weights", default="auto", metavar="{" + ",".join(WEIGHTS) + ",NAME}",
                    help="auto: the moving average when the run kept one (ema_decay), else "
                    "the optimizer's weights; raw: the optimizer's weights, written to "
                    "failures-raw.json; NAME: one of the run's average_probes (e.g. "
                    "ema0.9995), written to failures-NAME.json (default: auto)")  # fmt: skip
    pl = sub.add_parser("plot", help="loss and held-out FG-ARI of runs over wall time (PNG)")
    pl.add_argument("runs", nargs="+", metavar="LABEL=RUN_DIR")
    pl.add_argument("--out", required=True, help="PNG path")
    try:
        a = ap.parse_args(argv)
    except SystemExit as e:  # --help (0) or a usage error (2), already printed
        return int(e.code or 0)
    if a.cmd == "plot":
        runs = dict(x.split("=", 1) if "=" in x else (Path(x).name, x) for x in a.runs)
        missing = [r for r in runs.values() if not (Path(r) / "log.jsonl").is_file()]
        if missing:
            return fail(_PROG, f"plot: {missing[0]}: not a recipe run folder (no log.jsonl); "
                        "pass folders written by `train-eval` as LABEL=RUN_DIR")  # fmt: skip
        print(plot_runs(runs, a.out))
        return 0
    if a.cmd == "diagnose" and not (Path(a.run) / CHECKPOINT_NAME).is_file():
        return fail(_PROG, f"diagnose: no {CHECKPOINT_NAME} in {a.run} (not a run folder); "
                    "pass a folder written by `train-eval` or `svorf train`")  # fmt: skip
    if a.cmd == "train-eval" and not a.resume and (Path(a.out) / CHECKPOINT_NAME).exists():
        return fail(_PROG, f"train-eval: --out {a.out} already holds a run ({CHECKPOINT_NAME}); "
                    "pass --resume to continue it, or --out DIR to start a new run elsewhere")  # fmt: skip
    torch.set_num_threads(a.threads)
    if a.cmd == "diagnose":
        try:
            model, info = load_run(Path(a.run), weights=a.weights)
        except CheckpointError as err:
            return fail(_PROG, f"diagnose: {err}")
        except ValueError as err:  # not a name of weights
            return fail(_PROG, f"diagnose --weights: {err}")
        probe = dict(_parse_set(x, "--render-set") for x in a.render_set)
        try:
            render_probe(model, probe)
        except ValueError as err:
            return fail(_PROG, f"diagnose --render-set: {err}")
        test = MultiViewDataset(a.test, image_size=model.cfg.image_size, max_scenes=a.scenes)
        res = {"step": info.step, "weights": info.weights, "render_set": probe}
        occlusion = None
        if a.occlusion:
            from benchmark.tools.occlusion import SplitOcclusion

            occlusion = SplitOcclusion(a.test, test.image_hw[0])
        res.update(failure_breakdown(model, test, occlusion=occlusion))
        if a.depth:
            res["depth"] = depth_breakdown(model, test)
        name = "failures-probe.json" if probe else "failures.json"
        if a.weights not in ("auto", "ema") and not probe:
            name = f"failures-{a.weights}.json"
        atomic_write_json(Path(a.run) / name, res)
        if a.grid:
            res["grid"] = str(save_segmentation_grid(model, test, a.grid, a.grid_scenes))
        print(json.dumps(res, indent=2))
        return 0
    levers: dict[str, Any] = {}
    for name in ("ray_sampling", "nvs_warmup", "comp_temperature", "coord_frame"):
        if getattr(a, name) is not None:
            levers[name] = getattr(a, name)
    if a.fg_zmin is not None:
        levers["fg_zmin"] = a.fg_zmin if a.fg_zmin >= 0 else None
    if a.bg_outside_fg is not None:
        levers["bg_outside_fg"] = bool(a.bg_outside_fg)
    if a.fg_box is not None:
        levers["fg_box"] = a.fg_box if a.fg_box > 0 else None
    over = {k: getattr(a, k) for k in ("lr", "warmup", "batch_scenes", "rays_per_scene", "seed")
            if getattr(a, k) is not None}  # fmt: skip
    over.update(_parse_set(x, "--train-set") for x in a.train_set)
    try:
        mcfg, tcfg = recipe_configs(a.preset, levers, steps=1_000_000, eval_every=a.eval_every,
                                    eval_scenes=a.eval_scenes, ckpt_every=100, **over)  # fmt: skip
        if a.model_set:
            mcfg = mcfg.replace(**dict(_parse_set(x) for x in a.model_set))
    except (TypeError, ValueError) as err:  # an unknown field or a value its checks refuse
        return fail(_PROG, f"train-eval: {err}; see --model-set / --train-set")
    res = train_eval(a.data, a.test, a.out, a.minutes, mcfg, tcfg,
                     seg_metrics=None, resume=a.resume,
                     grid_scenes=a.grid_scenes, final_scenes=a.final_scenes,
                     train_scenes=a.train_scenes, init_from=a.init_from)  # fmt: skip
    print(json.dumps({"final": res["final"], "grid": res["grid"]}, indent=2))
    return 0


def _parse_set(item: str, flag: str = "--model-set") -> tuple[str, Any]:
    """ "field=value" -> (field, JSON value or the raw string)."""
    if "=" not in item:
        raise SystemExit(fail(_PROG, f"{flag} expects FIELD=VALUE, got {item!r}", USAGE))
    key, raw = item.split("=", 1)
    try:
        return key.strip(), json.loads(raw)
    except json.JSONDecodeError:
        return key.strip(), raw


if __name__ == "__main__":
    sys.exit(main())
