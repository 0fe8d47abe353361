"""Slot refinement: how much of a segmentation's error the encoder's single pass leaves
(diagnosis only).

A trained model's object fields are conditioned on slots that the encoder infers in one
forward pass from the input view. If the fields *could* draw an object's outline exactly
and only the inferred slots are off (the amortisation gap), then optimising the slots
alone, with every network frozen, to reproduce the scene's pixels moves the segmentation
towards the truth: the claimed rim narrows and ARI rises. If the error is in what the fields
can draw (their shape), refined slots fit the colours better and the segmentation stays.

:func:`refine_scene` refines one scene's slots (:func:`svorf.refine.refine_slots`); :func:`refinement_study` scores
held-out scenes before and after (input-view ARI, FG-ARI, the share of background pixels an
object slot claims, PSNR, and the same on the other views). ``fit="input"`` fits the input
view only, what the encoder saw; ``fit="all"`` fits every view of the scene (an oracle with
the novel views' pixels, a bound, never an evaluation). Ground truth is read only to score.

Command line::

    python -m benchmark.tools.refine RUN --test DATA/cpu/clevr567/test --scenes 10

writes ``refine-<fit>.json`` into the run folder and prints it.
"""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor

from benchmark.tools.failures import ari_repairs, fg_ari_repairs
from scenefmt import atomic_write_json
from scenefmt.cli_util import OneLineParser, doc_summary, fail
from svorf.checkpoint import WEIGHTS, CheckpointError, load_run
from svorf.data import MultiViewDataset
from svorf.model import SVORF
from svorf.refine import REFINE_LR, REFINE_RAYS, refine_slots

__all__ = ["FITS", "refine_scene", "refinement_study", "score_views"]

_PROG = "python -m benchmark.tools.refine"

#: Which views of a scene the slots are fitted to.
FITS = ("input", "all")


def _rays(sv: Any, views: list[int], device: torch.device) -> tuple[Tensor, Tensor, Tensor]:
    """(origins [N, 3], directions [N, 3], colours [N, 3]) of every pixel of ``views``."""
    o = sv.rays_o[views].reshape(-1, 3).to(device)
    d = sv.rays_d[views].reshape(-1, 3).to(device)
    rgb = sv.images[views].permute(0, 2, 3, 1).reshape(-1, 3).to(device)
    return o, d, rgb


def refine_scene(
    model: SVORF,
    sv: Any,
    input_view: int = 0,
    fit: str = "input",
    steps: int = 150,
    lr: float = REFINE_LR,
    rays: int = REFINE_RAYS,
    seed: int = 0,
) -> tuple[Tensor, Tensor, list[float]]:
    """The encoder's slots of one scene and slots refined on its pixels
    (:func:`svorf.refine.refine_slots`).

    Args:
        model: a trained model.
        sv: one scene of a :class:`MultiViewDataset` (``dataset[i]``).
        input_view: the view the encoder sees; its slots start the refinement.
        fit: "input" (fit that view's pixels, what ``--refine-slots`` does) or "all"
            (every view's: an oracle).
        steps, lr, rays, seed: as :func:`svorf.refine.refine_slots`.

    Returns:
        ``(encoded, refined, losses)``: slots [1, K, D] and the MSE of each step.
    """
    if fit not in FITS:
        raise ValueError(f"refine_scene: fit must be one of {list(FITS)}, got {fit!r}")
    device = next(model.parameters()).device
    views = [input_view] if fit == "input" else list(range(sv.images.shape[0]))
    o, d, rgb = _rays(sv, views, device)
    c2w = sv.cam_to_world[input_view : input_view + 1].to(device)
    with torch.no_grad():
        encoded = model.encode(sv.images[input_view : input_view + 1].to(device))
    refined, losses = refine_slots(
        model, encoded, o, d, rgb, steps=steps, lr=lr, rays=rays, input_c2w=c2w, seed=seed
    )
    return encoded, refined, losses


@torch.no_grad()
def score_views(model: SVORF, sv: Any, slots: Tensor, input_view: int = 0) -> dict[str, float]:
    """Segmentation and colour of every view of ``sv`` rendered from ``slots`` [1, K, D]:
    input-view ``ari``, ``fg_ari``, ``bleed_fraction`` (background pixels an object slot
    claims) and ``psnr``; ``nv_ari``, ``nv_fg_ari`` and ``nv_psnr``, the means over the
    other views (NaN without any)."""
    device = slots.device
    was = model.training
    model.eval()
    bg = model.cfg.num_slots - 1
    c2w = sv.cam_to_world[input_view : input_view + 1].to(device)
    v_n, _, h, w = sv.images.shape
    rows = []
    try:
        for v in range(v_n):
            o = sv.rays_o[v].reshape(1, h * w, 3).to(device)
            d = sv.rays_d[v].reshape(1, h * w, 3).to(device)
            out = model.render_chunked(slots, o, d, 4096, input_c2w=c2w)
            labels = out.slot_probs[0].argmax(-1).view(h, w).cpu()
            gt = sv.instances[v]
            mse = float(((out.rgb[0].view(h, w, 3).float().cpu()
                          - sv.images[v].permute(1, 2, 0)) ** 2).mean())  # fmt: skip
            a = ari_repairs(labels, gt, bg)
            rows.append({
                "ari": a["ari"],
                "fg_ari": fg_ari_repairs(labels, gt, bg)["fg_ari"],
                "bleed_fraction": a["bleed_fraction"],
                "psnr": -10.0 * math.log10(max(mse, 1e-10)),
            })  # fmt: skip
    finally:
        model.train(was)
    res = dict(rows[input_view])
    others = [r for v, r in enumerate(rows) if v != input_view]
    for k in ("ari", "fg_ari", "psnr"):
        res[f"nv_{k}"] = float(np.nanmean([r[k] for r in others])) if others else math.nan
    return res


def refinement_study(
    model: SVORF,
    ds: MultiViewDataset,
    n_scenes: int | None = None,
    input_view: int = 0,
    fit: str = "input",
    **refine_kw: Any,
) -> dict[str, Any]:
    """Score the first ``n_scenes`` scenes of ``ds`` (None = all) from the encoder's slots
    and from refined ones (:func:`refine_slots` with ``refine_kw``).

    Returns:
        ``encoded`` / ``refined``: the means over scenes of :func:`score_views` (x100 for the
        ARIs and the bleed fraction, dB for PSNR); ``delta``: refined minus encoded;
        ``loss_first`` / ``loss_last``: the mean photometric MSE of the first and last 10
        refinement steps; ``per_scene``; ``fit``, ``n_scenes`` and ``refine``.
    """
    n = len(ds) if n_scenes is None else min(int(n_scenes), len(ds))
    per_scene, first, last = [], [], []
    for i in range(n):
        sv = ds[i]
        if sv.instances is None:
            raise ValueError(f"refinement_study: {ds.root} has no instance ids (truth=False)")
        enc, ref, losses = refine_scene(model, sv, input_view, fit, seed=i, **refine_kw)
        per_scene.append({
            "scene": int(sv.scene),
            "encoded": score_views(model, sv, enc, input_view),
            "refined": score_views(model, sv, ref, input_view),
        })  # fmt: skip
        first.append(float(np.mean(losses[:10])))
        last.append(float(np.mean(losses[-10:])))

    def mean(which: str) -> dict[str, float]:
        keys = per_scene[0][which]
        scale = {k: (1.0 if "psnr" in k else 100.0) for k in keys}
        return {k: scale[k] * float(np.nanmean([s[which][k] for s in per_scene])) for k in keys}

    enc_m, ref_m = mean("encoded"), mean("refined")
    return {
        "fit": fit,
        "n_scenes": n,
        "refine": refine_kw,
        "encoded": enc_m,
        "refined": ref_m,
        "delta": {k: ref_m[k] - enc_m[k] for k in enc_m},
        "loss_first": float(np.mean(first)),
        "loss_last": float(np.mean(last)),
        "per_scene": per_scene,
    }


def main(argv: list[str] | None = None) -> int:
    """``python -m benchmark.tools.refine RUN --test DATA``; returns the exit status."""
    ap = OneLineParser(prog=_PROG, description=doc_summary(__doc__))
    ap.add_argument("run", help="a run folder (checkpoint.pt)")
    ap.add_argument("--test", required=True, help="held-out split with instance ids")
    ap.add_argument("--scenes", type=int, default=10, help="first N test scenes (default: 10)")
    ap.add_argument("--fit", choices=FITS, default="input",
                    help="fit the input view's pixels (default) or every view's (an oracle)")  # fmt: skip
    ap.add_argument("--steps", type=int, default=150, help="Adam steps per scene (default: 150)")
    ap.add_argument("--lr", type=float, default=REFINE_LR,
                    help=f"Adam learning rate (default: {REFINE_LR})")  # fmt: skip
    ap.add_argument("--rays", type=int, default=REFINE_RAYS,
                    help=f"random pixels per step (default: {REFINE_RAYS})")  # fmt: skip
    ap.add_argument("--threads", type=int, default=2, help="torch CPU threads")
    ap.add_argument("--weights", choices=WEIGHTS, default="auto",
                    help="auto: the moving average when the run kept one (default)")  # fmt: skip
    try:
        a = ap.parse_args(argv)
    except SystemExit as e:
        return int(e.code or 0)
    for name in ("scenes", "steps", "rays"):
        if getattr(a, name) < 1:
            return fail(_PROG, f"--{name} must be at least 1, got {getattr(a, name)}")
    if not a.lr > 0:
        return fail(_PROG, f"--lr must be positive, got {a.lr}")
    torch.set_num_threads(a.threads)
    try:
        model, info = load_run(Path(a.run), weights=a.weights)
    except CheckpointError as err:
        return fail(_PROG, str(err))
    if not Path(a.test).is_dir():
        return fail(_PROG, f"--test {a.test}: no such folder; pass a split folder such as "
                    "DATA/cpu/clevr567/test")  # fmt: skip
    test = MultiViewDataset(a.test, image_size=model.cfg.image_size, max_scenes=a.scenes)
    try:
        res = refinement_study(model, test, a.scenes, fit=a.fit, steps=a.steps, lr=a.lr,
                               rays=a.rays)  # fmt: skip
    except ValueError as err:
        return fail(_PROG, str(err))
    res = {"step": info.step, "weights": info.weights, **res}
    atomic_write_json(Path(a.run) / f"refine-{a.fit}.json", res)
    print(json.dumps({k: v for k, v in res.items() if k != "per_scene"}, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
