"""Where a trained model's held-out segmentation goes wrong, per object (diagnosis only).

Renders each test scene's input view and sorts every ground-truth object: lost to the
background slot, merged with another object into one foreground slot, or in a slot of its
own (:func:`object_failures`); scores what FG-ARI and ARI would be with one kind of error
repaired (:func:`fg_ari_repairs`, :func:`ari_repairs`); pools them with the rim's shape
(``benchmark.tools.rim``), how split objects lie (``benchmark.tools.splits``) and, on
request, how much of each object other objects hide (``benchmark.tools.occlusion``) in
:func:`failure_breakdown`; :func:`depth_breakdown` does the same for novel-view depth.
Ground truth is read only here, never in training. ``python -m benchmark.tools.recipe
diagnose`` is the command; ``train-eval`` writes :func:`failure_breakdown` into its final
evaluation.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import numpy as np
import torch
from torch import Tensor

from benchmark.tools.rim import dilate, rim_geometry, summarize_rim
from benchmark.tools.splits import split_geometry, summarize_splits
from svorf.ari import adjusted_rand_index
from svorf.data import MultiViewDataset
from svorf.model import SVORF
from svorf.predict import predict_scene

__all__ = [
    "ari_repairs",
    "depth_breakdown",
    "failure_breakdown",
    "fg_ari_repairs",
    "object_failures",
    "render_input_view",
    "summarize_failures",
]


@torch.no_grad()
def render_input_view(
    model: SVORF, ds: MultiViewDataset, scene: int, other: int, input_view: int
) -> tuple[Tensor, Tensor]:
    """(labels [H, W], rgb [H, W, 3]) of ``scene``'s input view alone, rendered from the
    slots of scene ``other`` (``other == scene``: its own) in ``scene``'s input-camera frame."""
    device = next(model.parameters()).device
    was = model.training
    model.eval()
    try:
        sv, so = ds[scene], ds[other]
        slots, extra = model.encode_for_render(so.images[input_view : input_view + 1].to(device))
        h, w = ds.image_hw
        o = sv.rays_o[input_view].reshape(1, h * w, 3).to(device)
        d = sv.rays_d[input_view].reshape(1, h * w, 3).to(device)
        c2w = sv.cam_to_world[input_view : input_view + 1].to(device)
        out = model.render_chunked(slots, o, d, 4096, input_c2w=c2w, **extra)
    finally:
        model.train(was)
    return out.slot_probs[0].argmax(-1).view(h, w).cpu(), out.rgb[0].view(h, w, 3).cpu()


def object_failures(pred: Tensor, gt: Tensor, bg_slot: int) -> list[dict[str, Any]]:
    """How each ground-truth object of one view is segmented.

    Every object (id != 0 of ``gt``) gets its dominant slot: the predicted label that
    covers most of its pixels. The object is ``"lost"`` when that is the background slot,
    ``"merged"`` when another object of the view has the same dominant foreground slot,
    else ``"own"`` (a slot of its own).

    Args:
        pred: int [H, W] predicted slot labels.
        gt: int [H, W] ground-truth instance ids, 0 = background.
        bg_slot: the background slot's label (K - 1).

    Returns:
        One dict per object, in id order: ``id``, ``pixels``, ``slot`` (dominant),
        ``share`` (its fraction of the object's pixels), ``kind`` ("lost", "merged", "own");
        merged objects also ``merged_with`` (the ids of the others in their slot).
    """
    if pred.shape != gt.shape:
        raise ValueError(f"object_failures: pred {tuple(pred.shape)} != gt {tuple(gt.shape)}")
    p, g = pred.reshape(-1).long(), gt.reshape(-1).long()
    rows = []
    for oid in torch.unique(g).tolist():
        if oid == 0:
            continue
        labels = p[g == oid]
        counts = torch.bincount(labels)
        slot = int(counts.argmax())
        share = float(counts[slot]) / labels.numel()
        rows.append({"id": int(oid), "pixels": int(labels.numel()), "slot": slot, "share": share})
    fg_slots = [r["slot"] for r in rows if r["slot"] != bg_slot]
    for r in rows:
        if r["slot"] == bg_slot:
            r["kind"] = "lost"
        elif fg_slots.count(r["slot"]) > 1:
            r["kind"] = "merged"
            r["merged_with"] = [q["id"] for q in rows if q["slot"] == r["slot"] and q is not r]
        else:
            r["kind"] = "own"
    return rows


def fg_ari_repairs(pred: Tensor, gt: Tensor, bg_slot: int) -> dict[str, float]:
    """FG-ARI of one view as predicted and with one kind of error repaired (diagnosis only).

    Says where the FG-ARI points go: the repaired scores are what FG-ARI would be if that
    error alone were gone, the rest of the prediction unchanged.

    Args:
        pred: int [H, W] predicted slot labels.
        gt: int [H, W] ground-truth instance ids, 0 = background.
        bg_slot: the background slot's label (K - 1).

    Returns:
        ``fg_ari``: as predicted. ``bg_leak_repaired``: every object pixel labelled with the
        background slot gets a label of its own per object (objects lost to the background
        and object pixels leaking into it, e.g. rims, are then found). ``split_repaired``:
        every object pixel in a foreground slot other than its object's dominant foreground
        slot gets that dominant slot (objects cut between slots, rims of neighbours).
        ``merge_repaired``: objects that share their dominant foreground slot with another
        object get a label of their own for that slot's pixels. NaN on a view without
        objects.
    """
    if pred.shape != gt.shape:
        raise ValueError(f"fg_ari_repairs: pred {tuple(pred.shape)} != gt {tuple(gt.shape)}")
    p, g = pred.reshape(-1).long(), gt.reshape(-1).long()
    fg = g != 0
    if not bool(fg.any()):
        nan = math.nan
        return {
            "fg_ari": nan,
            "bg_leak_repaired": nan,
            "split_repaired": nan,
            "merge_repaired": nan,
        }
    fresh = int(max(int(p.max()), bg_slot)) + 1  # labels no slot uses
    leak, split, merge = p.clone(), p.clone(), p.clone()
    dominant: dict[int, int] = {}
    for oid in torch.unique(g[fg]).tolist():
        obj = g == oid
        leak[obj & (p == bg_slot)] = fresh + oid
        labels = p[obj]
        fg_labels = labels[labels != bg_slot]
        if fg_labels.numel():
            dom = int(torch.bincount(fg_labels).argmax())
            dominant[oid] = dom
            split[obj & (p != bg_slot)] = dom
    owners: dict[int, list[int]] = {}
    for oid, dom in dominant.items():
        owners.setdefault(dom, []).append(oid)
    for dom, oids in owners.items():
        for oid in oids[1:]:  # the first keeps the slot, the others get labels of their own
            merge[(g == oid) & (p == dom)] = fresh + 1000 + oid
    return {
        name: adjusted_rand_index(x, g, fg)
        for name, x in (("fg_ari", p), ("bg_leak_repaired", leak), ("split_repaired", split),
                        ("merge_repaired", merge))
    }  # fmt: skip


def ari_repairs(pred: Tensor, gt: Tensor, bg_slot: int) -> dict[str, float]:
    """ARI (background included) of one view, with one kind of error repaired (diagnosis only).

    ARI, unlike FG-ARI, scores the background pixels too, so at low resolution the one-pixel
    rim an object slot claims around its object costs ARI points that FG-ARI never sees.

    Args:
        pred: int [H, W] predicted slot labels.
        gt: int [H, W] ground-truth instance ids, 0 = background.
        bg_slot: the background slot's label (K - 1).

    Returns:
        ``ari``: as predicted. ``bleed_repaired``: ground-truth background pixels claimed by an
        object slot get the background slot. ``lost_repaired``: object pixels in the background
        slot get a label of their own per object. ``bleed_fraction``: the share of background
        pixels claimed by an object slot; ``bleed_within_1px`` / ``bleed_within_2px``: the
        share of those pixels at most 1 / 2 pixels (chessboard distance) from an object
        (NaN when none bleed). ``rim_ceiling``: the ARI of the ground truth with every object
        grown by one pixel into the background (what a one-pixel rim alone costs).
    """
    if pred.shape != gt.shape or pred.dim() != 2:
        raise ValueError(f"ari_repairs: pred {tuple(pred.shape)} and gt {tuple(gt.shape)} "
                         "must be the same [H, W]")  # fmt: skip
    p, g = pred.long(), gt.long()
    bleed = (g == 0) & (p != bg_slot)
    fixed_bleed = torch.where(bleed, torch.full_like(p, bg_slot), p)
    fresh = int(max(int(p.max()), bg_slot)) + 1  # labels no slot uses
    fixed_lost = torch.where((g != 0) & (p == bg_slot), fresh + g, p)
    obj = g != 0
    n_bleed = int(bleed.sum())
    grown = torch.nn.functional.max_pool2d(g[None, None].float(), 3, 1, 1)[0, 0].long()
    rim = torch.where(obj, g, grown)  # max id wins where two objects' rims meet
    n_bg = int((~obj).sum())
    return {
        "ari": adjusted_rand_index(p, g),
        "bleed_repaired": adjusted_rand_index(fixed_bleed, g),
        "lost_repaired": adjusted_rand_index(fixed_lost, g),
        "bleed_fraction": n_bleed / n_bg if n_bg else math.nan,
        "bleed_within_1px": int((bleed & dilate(obj, 1)).sum()) / n_bleed if n_bleed else math.nan,
        "bleed_within_2px": int((bleed & dilate(obj, 2)).sum()) / n_bleed if n_bleed else math.nan,
        "rim_ceiling": adjusted_rand_index(rim, g),
    }


@torch.no_grad()
def depth_breakdown(
    model: SVORF, ds: MultiViewDataset, n_scenes: int | None = None, input_view: int = 0
) -> dict[str, float]:
    """Where the novel-view depth error lies: objects, and background inside / outside the
    region the model samples (diagnosis only; ground truth is read only here).

    With ``clip_to_box`` a ray's samples stay in the box ``|x|, |y| <= box_half``, so
    background whose true point lies beyond it (floor seen far away) cannot get its depth
    right: the box wall stands in for it and the floor looks like a bowl.

    Returns:
        ``abs_rel_objects``, ``abs_rel_bg_inside``, ``abs_rel_bg_outside`` (mean over
        pixels of |pred - gt| / gt, novel views of the first ``n_scenes`` scenes, NaN where a
        region is empty), ``bg_outside_share`` (share of background pixels whose true point
        is outside the sampled box; 0 without ``clip_to_box``), ``n_scenes``.
    """
    n = len(ds) if n_scenes is None else min(int(n_scenes), len(ds))
    half = model.cfg.box_half if model.cfg.clip_to_box else math.inf
    err: dict[str, list[Tensor]] = {"objects": [], "bg_inside": [], "bg_outside": []}
    for i in range(n):
        sv = ds[i]
        if sv.instances is None or sv.depth_z is None:
            raise ValueError(f"depth_breakdown: {ds.root} has no instance ids or depth")
        pred = predict_scene(model, ds, i, input_view=input_view).depth_z
        for v in range(sv.images.shape[0]):
            if v == input_view:
                continue
            gt = sv.depth_z[v]
            ok = torch.isfinite(gt) & (gt > 0)
            rel = (pred[v] - gt).abs() / gt
            pts = sv.rays_o[v] + sv.rays_d[v] * (gt / sv.z_scale[v])[..., None]
            outside = (pts[..., :2].abs() > half).any(-1)
            bg = ok & (sv.instances[v] == 0)
            err["objects"].append(rel[ok & (sv.instances[v] != 0)])
            err["bg_inside"].append(rel[bg & ~outside])
            err["bg_outside"].append(rel[bg & outside])
    out = {}
    for k, xs in err.items():
        x = torch.cat(xs) if xs else torch.zeros(0)
        out[f"abs_rel_{k}"] = float(x.mean()) if x.numel() else math.nan
    n_in = sum(x.numel() for x in err["bg_inside"])
    n_out = sum(x.numel() for x in err["bg_outside"])
    out["bg_outside_share"] = n_out / (n_in + n_out) if n_in + n_out else math.nan
    out["n_scenes"] = float(n)
    return out


def _nanmean(xs: list[float]) -> float:
    """Mean of the non-NaN values; NaN (without numpy's empty-slice warning) when none."""
    kept = [x for x in xs if not math.isnan(x)]
    return float(np.mean(kept)) if kept else math.nan


def summarize_failures(rows: list[dict[str, Any]]) -> dict[str, Any]:
    """Fractions and sizes of :func:`object_failures` rows (any number of views/scenes).

    Returns ``objects``; per kind ("lost", "merged", "own"): ``fraction`` of the objects,
    ``median_pixels``; ``own_share``: the mean pixel share of the "own" objects' slots
    (NaN where a group is empty).
    """
    out: dict[str, Any] = {"objects": len(rows)}
    for kind in ("lost", "merged", "own"):
        px = [r["pixels"] for r in rows if r["kind"] == kind]
        out[kind] = {
            "fraction": len(px) / len(rows) if rows else math.nan,
            "median_pixels": float(np.median(px)) if px else math.nan,
        }
    own = [r["share"] for r in rows if r["kind"] == "own"]
    out["own_share"] = float(np.mean(own)) if own else math.nan
    return out


@torch.no_grad()
def failure_breakdown(
    model: SVORF,
    ds: MultiViewDataset,
    n_scenes: int | None = None,
    input_view: int = 0,
    occlusion: Callable[[int, int], dict[int, dict[str, Any]]] | None = None,
) -> dict[str, Any]:
    """Where the input-view segmentation of held-out scenes goes wrong, per object.

    Renders the input view of the first ``n_scenes`` scenes (None = all) and classifies
    every object with :func:`object_failures`: lost to the background slot, merged with
    another object into one foreground slot, or in a slot of its own. Also the mean absolute
    reconstruction error (colour units) over each kind's pixels: an object lost to the
    background but reconstructed was painted onto the background; one that is not, was not
    rendered at all. Ground truth is read only here, never in training.

    Returns:
        :func:`summarize_failures` of all objects, plus ``rgb_abs_err`` per kind,
        ``fg_ari_repairs`` and ``ari_repairs`` (the means over scenes of
        :func:`fg_ari_repairs` and :func:`ari_repairs`), ``rim`` (the rim's shape,
        :func:`benchmark.tools.rim.summarize_rim`: an offset or a dilation), ``splits``
        (how split objects lie, :func:`benchmark.tools.splits.summarize_splits`) and
        ``n_scenes``. With ``occlusion`` (``(scene number, view) -> {id: {"hidden",
        "occluders", ...}}``, e.g. ``benchmark.tools.occlusion.SplitOcclusion``) also
        ``occlusion``: ``benchmark.tools.occlusion.summarize_occlusion`` of the objects.
    """
    n = len(ds) if n_scenes is None else min(int(n_scenes), len(ds))
    bg = model.cfg.num_slots - 1
    rows: list[dict[str, Any]] = []
    repairs: list[dict[str, float]] = []
    ari_rows: list[dict[str, float]] = []
    rims: list[dict[str, Any]] = []
    splits: list[dict[str, Any]] = []
    for i in range(n):
        sv = ds[i]
        if sv.instances is None:
            raise ValueError(f"failure_breakdown: {ds.root} has no instance ids (truth=False)")
        labels, rgb = render_input_view(model, ds, i, i, input_view)  # that view only
        gt = sv.instances[input_view]
        image = sv.images[input_view].permute(1, 2, 0)
        err = (rgb - image).abs().mean(-1)
        repairs.append(fg_ari_repairs(labels, gt, bg))
        ari_rows.append(ari_repairs(labels, gt, bg))
        rims.append(rim_geometry(labels, gt, bg, image=image, render=rgb))
        splits.extend(split_geometry(labels, gt, bg))
        occ = occlusion(ds.scene_ids[i], input_view) if occlusion is not None else {}
        for r in object_failures(labels, gt, bg):
            r["err"] = float(err[gt == r["id"]].mean())
            if occlusion is not None:
                o = occ.get(r["id"], {"hidden": 0.0, "occluders": []})
                r["hidden"], r["occluders"] = o["hidden"], o["occluders"]
            rows.append(r)
    out = summarize_failures(rows)
    out["rgb_abs_err"] = {
        kind: (float(np.mean(e)) if e else math.nan)
        for kind in ("lost", "merged", "own")
        for e in [[r["err"] for r in rows if r["kind"] == kind]]
    }
    out["fg_ari_repairs"] = {
        k: _nanmean([r[k] for r in repairs])
        for k in ("fg_ari", "bg_leak_repaired", "split_repaired", "merge_repaired")
    }
    out["ari_repairs"] = {
        k: _nanmean([r[k] for r in ari_rows])
        for k in ("ari", "bleed_repaired", "lost_repaired", "bleed_fraction",
                  "bleed_within_1px", "bleed_within_2px", "rim_ceiling")
    }  # fmt: skip
    out["rim"] = summarize_rim(rims)
    out["splits"] = summarize_splits(splits)
    if occlusion is not None:
        from benchmark.tools.occlusion import summarize_occlusion

        out["occlusion"] = summarize_occlusion(rows)
    out["n_scenes"] = n
    return out
