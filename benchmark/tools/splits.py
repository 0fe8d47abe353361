"""How objects split between two foreground slots lie: top and bottom, or side by side.

Diagnosis only (ground truth is read here, never in training). An object of one view is
*split* when a second foreground slot holds at least ``min_share`` of its pixels (and at
least ``min_pixels``) beside
its dominant foreground slot. The split lies *top and bottom* when the second slot's pixels
sit further from the dominant slot's pixels along the image rows than along the columns;
``second_below`` counts those where the second slot holds the lower part of the object.
``python -m benchmark.tools.recipe diagnose`` reports the summary as ``splits``.
"""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor

__all__ = ["split_geometry", "summarize_splits"]


def split_geometry(
    pred: Tensor, gt: Tensor, bg_slot: int, min_share: float = 0.15, min_pixels: int = 3
) -> list[dict[str, Any]]:
    """One dict per ground-truth object of one view: ``pixels``, ``split`` (bool) and, when
    split, ``dy`` / ``dx``: the second slot's pixel centroid minus the dominant slot's (rows
    down, columns right).

    Args:
        pred: int [H, W] predicted slot labels.
        gt: int [H, W] ground-truth instance ids, 0 = background.
        bg_slot: the background slot's label (K - 1).
        min_share: the least share of the object's pixels the second slot must hold.
        min_pixels: the least number of pixels it must hold.
    """
    if pred.shape != gt.shape:
        raise ValueError(f"split_geometry: pred {tuple(pred.shape)} != gt {tuple(gt.shape)}")
    p, g = pred.long(), gt.long()
    rows = []
    for oid in torch.unique(g).tolist():
        if oid == 0:
            continue
        ys, xs = torch.nonzero(g == oid, as_tuple=True)
        lab = p[ys, xs]
        row: dict[str, Any] = {"pixels": int(ys.numel()), "split": False}
        counts = torch.bincount(lab[lab != bg_slot], minlength=max(int(p.max()), bg_slot) + 1)
        dom = int(counts.argmax())
        counts[dom] = 0
        sec = int(counts.argmax())
        if int(counts[sec]) >= max(min_pixels, 1, min_share * ys.numel()):
            a, b = lab == dom, lab == sec
            row.update(
                split=True,
                dy=float(ys[b].float().mean() - ys[a].float().mean()),
                dx=float(xs[b].float().mean() - xs[a].float().mean()),
            )
        rows.append(row)
    return rows


def summarize_splits(rows: list[dict[str, Any]], large: int = 30) -> dict[str, int]:
    """Counts over :func:`split_geometry` rows of many views: ``objects``, ``split``,
    ``split_large`` (objects of ``large`` pixels or more), ``top_bottom`` (|dy| > |dx|) and
    ``second_below`` (top and bottom, the second slot lower in the image)."""
    split = [r for r in rows if r["split"]]
    tb = [r for r in split if abs(r["dy"]) > abs(r["dx"])]
    return {
        "objects": len(rows),
        "split": len(split),
        "split_large": sum(r["pixels"] >= large for r in split),
        "top_bottom": len(tb),
        "second_below": sum(r["dy"] > 0 for r in tb),
    }
