"""The shape of the rim an object slot claims around its object (diagnosis only).

At low resolution a predicted object mask one pixel too wide costs ARI points that FG-ARI
never sees (``benchmark.tools.failures.ari_repairs``). Two causes look alike in ARI and
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


#: The least colour difference (Euclidean, 0-1 RGB) between an object and its floor for
#: :func:`ring_colour_share` to measure the share of the object's colour in its ring.
MIN_CONTRAST = 0.15


def ring_colour_share(
    pred: Tensor, gt: Tensor, bg_slot: int, image: Tensor, render: Tensor | None = None
) -> list[tuple[float, float, bool]]:
    """How much of its object's colour each background pixel next to an object holds.

    Per object with at least 3 interior pixels (the object eroded by one) whose median
    colour differs from the floor's (the median of the background 4-6 pixels away) by at
    least :data:`MIN_CONTRAST`, and per background pixel 8-connected to it: its colour's
    position between floor (0) and object (1) along that difference, in the ground-truth
    ``image`` and in the model's ``render`` (nan without one), and whether an object slot
    claims it. The pixel filter blends an object into the pixels around it (the share in
    ``image``); a share in ``render`` well above it means the model draws the object's edge
    wider than it is, one near 0 on a claimed pixel that an object slot paints floor colour.

    Args:
        pred, gt, bg_slot: as :func:`rim_geometry`.
        image: float [H, W, 3] the view's ground-truth colours.
        render: float [H, W, 3] the model's rendering of the view, or None.

    Returns:
        ``(share_in_image, share_in_render, claimed)`` per ring pixel.
    """
    p, g = pred.long(), gt.long()
    img = image.double()
    bg = g == 0
    out: list[tuple[float, float, bool]] = []
    for oid in g.unique().tolist():
        if oid == 0:
            continue
        o = g == oid
        core = ~dilate(~o, 1)
        far = dilate(o, 6) & ~dilate(o, 3) & bg
        ring = dilate(o, 1) & bg
        if int(core.sum()) < 3 or int(far.sum()) < 5 or not bool(ring.any()):
            continue
        floor = img[far].median(dim=0).values
        axis = img[core].median(dim=0).values - floor
        if float(axis.norm()) < MIN_CONTRAST:
            continue
        share = ((img[ring] - floor) @ axis) / (axis @ axis)
        if render is None:
            rshare = torch.full_like(share, math.nan)
        else:
            rshare = ((render.double()[ring] - floor) @ axis) / (axis @ axis)
        claimed = p[ring] != bg_slot
        out.extend(zip(share.tolist(), rshare.tolist(), claimed.tolist()))
    return out


def rim_geometry(
    pred: Tensor,
    gt: Tensor,
    bg_slot: int,
    image: Tensor | None = None,
    render: Tensor | None = None,
) -> dict[str, Any]:
    """Where one view's predicted objects lie against the ground truth.

    Args:
        pred: int [H, W] predicted slot labels.
        gt: int [H, W] ground-truth instance ids, 0 = background.
        bg_slot: the background slot's label.
        image, render: float [H, W, 3] the view's true colours and the model's rendering;
            with ``image``, ``ring_share`` is :func:`ring_colour_share`.

    Returns:
        ``shifts``: per object that keeps at least half its pixels in foreground slots,
        ``(dx, dy, gt_pixels, pred_pixels)``: the centroid of its dominant slot's pixels
        within two pixels of it minus its own centroid (image x right, y down), and both
        areas. ``ring`` / ``claimed``: per side (``left`` = the background pixel lies left
        of an object pixel), the background pixels next to an object on that side, and
        those an object slot claims. ``ring_share`` (with ``image``): see above.
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
    out: dict[str, Any] = {"shifts": shifts, "ring": ring, "claimed": claimed}
    if image is not None:
        out["ring_share"] = ring_colour_share(p, g, bg_slot, image, render)
    return out


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
    if any("ring_share" in v for v in views):
        out["ring_colour_share"] = _summarize_share(
            [r for v in views for r in v.get("ring_share", [])]
        )
    return out


def _summarize_share(rows: list[tuple[float, float, bool]]) -> dict[str, Any]:
    """Medians of :func:`ring_colour_share` over the claimed and the unclaimed ring pixels:
    the object's share of the true and the rendered colour, and the fraction of pixels whose
    true colour is more object than floor."""
    out: dict[str, Any] = {}
    for name, want in (("claimed", True), ("unclaimed", False)):
        t = torch.tensor([(a, b) for a, b, c in rows if c is want], dtype=torch.float64)
        n = len(t)
        out[name] = {
            "pixels": n,
            "share_in_image_median": float(t[:, 0].median()) if n else math.nan,
            "share_in_render_median": float(t[:, 1].nanmedian()) if n else math.nan,
            "image_over_half": float((t[:, 0] > 0.5).double().mean()) if n else math.nan,
        }
    return out
