"""Adjusted Rand index (ARI) of label maps, equal to ``sklearn.metrics.adjusted_rand_score``.

Where this sits: the one ARI of the project. ``benchmark.tools.recipe`` scores its held-out
segmentation with it during training, and ``benchmark.metrics.segmentation`` (ARI,
FG-ARI, NV-ARI, ARI*, FG-ARI* of the reports) checks its inputs and calls it through the
benchmark's adapter. Label maps in, float64 scores out; nothing here knows about models.

The index is computed per batch row from a sparse contingency table with float64 pair
counts and follows ``sklearn.metrics.adjusted_rand_score`` exactly, including its
degenerate case (no disagreeing pair => 1.0: both labelings a single cluster, both
all-singletons, a single pixel). The one deliberate difference: a row with *no* pixel
left (e.g. FG-ARI on a view without foreground) gives NaN here, where sklearn returns 1.0
for empty input (tests/test_ari.py checks both against sklearn).

Example:
    >>> import torch
    >>> gt = torch.tensor([[0, 0, 1, 1, 2, 2]])
    >>> pred = torch.tensor([[5, 5, 3, 3, 7, 7]])  # same partition, other names
    >>> ari_rows(pred, gt, torch.ones_like(gt, dtype=torch.bool))
    tensor([1.], dtype=torch.float64)
    >>> adjusted_rand_index(torch.tensor([0, 0, 1, 2, 1, 2]), gt[0])
    0.16666666666666666
"""

from __future__ import annotations

import torch
from torch import Tensor

__all__ = ["adjusted_rand_index", "ari_rows"]


def ari_rows(pred: Tensor, gt: Tensor, valid: Tensor) -> Tensor:
    """ARI per batch row over the ``valid`` pixels.

    Args:
        pred: integer ``[B, P]`` predicted labels (any values; only the partition matters).
        gt: integer ``[B, P]`` ground-truth labels.
        valid: bool ``[B, P]``, the pixels scored.

    Returns:
        Float64 ``[B]``: ARI in [-1, 1] per row, NaN for a row with no valid pixel.

    The inputs are not checked (``benchmark.metrics.ari`` checks them and names what is
    wrong); ``pred`` and ``gt`` must be int64 of one shape.
    """
    batch = pred.shape[0]
    device = pred.device
    f64 = torch.float64
    if batch == 0:
        return torch.empty(0, dtype=f64, device=device)
    # Compact the labels to 0..n-1 over the whole batch so the table index stays
    # small whatever the label values are (instance ids, slot indices).
    _, p = torch.unique(pred, return_inverse=True)
    _, g = torch.unique(gt, return_inverse=True)
    n_p = int(p.max()) + 1 if p.numel() else 1
    n_g = int(g.max()) + 1 if g.numel() else 1
    rows = torch.arange(batch, device=device).unsqueeze(1).expand_as(p)
    b_v, p_v, g_v = rows[valid], p[valid], g[valid]

    # Sparse contingency table: counts n_ij of the (row, pred, gt) triples present.
    # Only sums of squared counts enter the pair counts, so the dense table
    # (which can be P x P for all-distinct labels) is never built.
    cells_per_row = n_p * n_g
    keys, cell_counts = torch.unique((b_v * n_p + p_v) * n_g + g_v, return_counts=True)
    cell_counts = cell_counts.to(f64)
    sum_sq = torch.zeros(batch, dtype=f64, device=device)
    sum_sq.index_add_(0, keys // cells_per_row, cell_counts * cell_counts)
    pred_sizes = torch.bincount(b_v * n_p + p_v, minlength=batch * n_p).to(f64)
    gt_sizes = torch.bincount(b_v * n_g + g_v, minlength=batch * n_g).to(f64)
    sum_pred_sq = (pred_sizes * pred_sizes).view(batch, n_p).sum(1)
    sum_gt_sq = (gt_sizes * gt_sizes).view(batch, n_g).sum(1)
    n = valid.sum(1).to(f64)

    # Ordered pair counts exactly as sklearn.metrics.cluster.pair_confusion_matrix.
    # All of them are integers below 2**53 for P < 9.4e7, hence exact in float64.
    tp = sum_sq - n
    fp = sum_pred_sq - sum_sq  # same predicted cluster, different gt cluster
    fn = sum_gt_sq - sum_sq  # same gt cluster, different predicted cluster
    tn = n * n - fp - fn - sum_sq
    agree = (fp == 0) & (fn == 0)  # sklearn: "empty data or full agreement" -> 1.0
    denom = (tp + fn) * (fn + tn) + (tp + fp) * (fp + tn)
    score = 2.0 * (tp * tn - fn * fp) / torch.where(agree, torch.ones_like(denom), denom)
    score = torch.where(agree, torch.ones_like(score), score)
    return torch.where(n == 0, torch.full_like(score, float("nan")), score)


def adjusted_rand_index(pred: Tensor, gt: Tensor, mask: Tensor | None = None) -> float:
    """ARI of two integer labelings of the same pixels (optionally only where ``mask``).

    Args:
        pred: integer labels, any shape.
        gt: integer labels, the same number of elements.
        mask: optional bool (or 0/1) tensor, the same number of elements: pixels scored.

    Returns:
        The ARI as a float (sklearn's ``adjusted_rand_score`` of the scored pixels); NaN
        when no pixel is scored.
    """
    p = pred.reshape(1, -1).long()
    g = gt.reshape(1, -1).long()
    if p.shape != g.shape:
        raise ValueError(
            f"adjusted_rand_index: pred has {p.shape[1]} labels, gt {g.shape[1]}; expected "
            "the same pixels"
        )
    keep = torch.ones_like(p, dtype=torch.bool) if mask is None else mask.reshape(1, -1).bool()
    if keep.shape != p.shape:
        raise ValueError(
            f"adjusted_rand_index: mask has {keep.shape[1]} elements, pred {p.shape[1]}; "
            "expected one per pixel"
        )
    return float(ari_rows(p, g, keep)[0])
