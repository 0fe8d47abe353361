"""The shape of the rim an object slot claims around its object (diagnosis only).

At low resolution a predicted object mask one pixel too wide costs ARI points that FG-ARI
never sees (``benchmark.tools.recipe.ari_repairs``). Two causes look alike in ARI and
differ here: a convention error (a half-pixel offset between the rays the model renders and
the pixels the ground truth labels) moves every predicted object the same way, while a
model that paints its objects too wide grows them on every side. :func:`rim_geometry`
tells them apart per view; :func:`summarize_rim` pools views.

Example:
    >>> import torch
    >>> gt = torch.zeros(6, 6, dtype=torch.long); gt[2:4, 2:4] = 1
    >>> pred = torch.full((6, 6), 3); pred[2:4, 3:5] = 0   # the object one pixel right
    >>> r = summarize_rim([rim_geometry(pred, gt, bg_slot=3)])
    >>> r["centroid_shift_px"]["x"], r["claimed_by_side"]["left"], r["claimed_by_side"]["right"]
    (1.0, 0.0, 1.0)
"""

from __future__ import annotations

import math
from typing import Any

import torch
from torch import Tensor

#: (dy, dx) of the object neighbour that puts a background pixel on that side of it.
_SIDES = {"left": (0, 1), "right": (0, -1), "above": (1, 0), "below": (-1, 0)}


def _neighbour(mask: Tensor, dy: int, dx: int) -> Tensor:
    """Bool [H, W]: ``mask`` at (y + dy, x + dx) (False beyond the image)."""
    h, w = mask.shape
    out = torch.zeros_like(mask)
    out[max(-dy, 0) : h - max(dy, 0), max(-dx, 0) : w - max(dx, 0)] = mask[
        max(dy, 0) : h - max(-dy, 0), max(dx, 0) : w - max(-dx, 0)
    ]
    return out


def dilate(mask: Tensor, radius: int) -> Tensor:
    """Bool [H, W] ``mask`` grown by ``radius`` pixels (8-connected, i.e. a square)."""
    m = mask.float()[None, None]
    return torch.nn.functional.max_pool2d(m, 2 * radius + 1, 1, radius)[0, 0] > 0


def rim_geometry(pred: Tensor, gt: Tensor, bg_slot: int) -> dict[str, Any]:
    """Where one view's predicted objects lie against the ground truth.

    Args:
        pred: int [H, W] predicted slot labels.
        gt: int [H, W] ground-truth instance ids, 0 = background.
        bg_slot: the background slot's label.

    Returns:
        ``shifts``: per object that keeps at least half its pixels in foreground slots,
        ``(dx, dy, gt_pixels, pred_pixels)``: the centroid of its dominant slot's pixels
        within two pixels of it minus its own centroid (image x right, y down), and both
        areas. ``ring`` / ``claimed``: per side (``left`` = the background pixel lies left
        of an object pixel), the background pixels next to an object on that side, and
        those an object slot claims.
    """
    if pred.shape != gt.shape or pred.dim() != 2:
        raise ValueError(f"rim_geometry: pred {tuple(pred.shape)} and gt {tuple(gt.shape)} "
                         "must be the same [H, W]")  # fmt: skip
    p, g = pred.long(), gt.long()
    obj = g != 0
    bleed = ~obj & (p != bg_slot)
    ring, claimed = {}, {}
    for side, (dy, dx) in _SIDES.items():
        edge = ~obj & _neighbour(obj, dy, dx)
        ring[side], claimed[side] = int(edge.sum()), int((edge & bleed).sum())
    ys, xs = torch.meshgrid(
        torch.arange(g.shape[0], dtype=torch.float64),
        torch.arange(g.shape[1], dtype=torch.float64),
        indexing="ij",
    )
    shifts = []
    for oid in g.unique().tolist():
        if oid == 0:
            continue
        o = g == oid
        fg = p[o][p[o] != bg_slot]
        if 2 * fg.numel() < int(o.sum()):
            continue  # mostly lost to the background: no shape to compare
        dom = int(torch.bincount(fg).argmax())
        po = (p == dom) & dilate(o, 2)
        dx = float(xs[po].mean() - xs[o].mean())
        dy = float(ys[po].mean() - ys[o].mean())
        shifts.append((dx, dy, int(o.sum()), int(po.sum())))
    return {"shifts": shifts, "ring": ring, "claimed": claimed}


def summarize_rim(views: list[dict[str, Any]]) -> dict[str, Any]:
    """Pool :func:`rim_geometry` over views: the mean centroid shift in pixels (with its
    standard error; an offset in the conventions shows as a mean far from 0 in units of
    it), the median ratio of predicted to true area, and per side the share of the
    background pixels next to an object that object slots claim."""
    shifts = [s for v in views for s in v["shifts"]]
    sides = list(_SIDES)
    ring = {s: sum(v["ring"][s] for v in views) for s in sides}
    claimed = {s: sum(v["claimed"][s] for v in views) for s in sides}
    out: dict[str, Any] = {"objects": len(shifts)}
    if shifts:
        t = torch.tensor(shifts, dtype=torch.float64)
        sem = t[:, :2].std(dim=0) / math.sqrt(len(t)) if len(t) > 1 else torch.full((2,), math.nan)
        out["centroid_shift_px"] = {"x": float(t[:, 0].mean()), "y": float(t[:, 1].mean())}
        out["centroid_shift_sem_px"] = {"x": float(sem[0]), "y": float(sem[1])}
        out["area_ratio_median"] = float((t[:, 3] / t[:, 2]).median())
    else:
        out["centroid_shift_px"] = {"x": math.nan, "y": math.nan}
        out["centroid_shift_sem_px"] = {"x": math.nan, "y": math.nan}
        out["area_ratio_median"] = math.nan
    out["claimed_by_side"] = {s: claimed[s] / ring[s] if ring[s] else math.nan for s in sides}
    return out
