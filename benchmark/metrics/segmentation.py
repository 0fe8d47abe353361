"""Segmentation metrics: ARI, FG-ARI, NV-ARI and the pooled ARI* / FG-ARI*.

Where this sits: the benchmark protocols (``segmentation``, ``generalization``,
``ablation``...) render a model's slot masks for every view of a scene, take the
arg-max slot per pixel, and call :func:`segmentation_metrics` with the ground-truth
instance maps of the dataset (instance id 0 = background, k = object k). Nothing
here knows about models or files: label maps in, per-scene float64 scores out.

The adjusted Rand index is svorf's (``svorf.ari.ari_rows``, the project's one ARI, a
pure function of label maps); this module checks the inputs and builds the scores from
it. It is computed per batch row from a sparse contingency table with float64 pair
counts and follows ``sklearn.metrics.adjusted_rand_score`` exactly, including its
degenerate case (no disagreeing pair => 1.0, e.g. both labelings a single cluster, both
all-singletons, or a single pixel). The one deliberate difference: a row with *no* pixel
left (e.g. FG-ARI on a view without foreground) gives NaN here, where sklearn returns 1.0
for empty input; protocols aggregate with ``nanmean`` and report how many rows were NaN.

Example:
    >>> import torch
    >>> gt = torch.tensor([[0, 0, 1, 1, 2, 2]])
    >>> pred = torch.tensor([[5, 5, 3, 3, 7, 7]])  # same partition, other names
    >>> ari_score(pred, gt)
    tensor([1.], dtype=torch.float64)
"""

from __future__ import annotations

import torch
from torch import Tensor

from benchmark.metrics._checks import (
    describe,
    require_batched,
    require_integer,
    require_same_shape,
    require_tensor,
)
from svorf.ari import ari_rows

__all__ = [
    "SEGMENTATION_KEYS",
    "ari",
    "ari_score",
    "fg_ari_score",
    "segmentation_metrics",
]

#: Keys of the dict returned by :func:`segmentation_metrics`, in report order.
SEGMENTATION_KEYS: tuple[str, ...] = (
    "ari",
    "fg_ari",
    "nv_ari",
    "nv_fg_ari",
    "nv_ari_last",
    "ari_all",
    "fg_ari_all",
)

_LABELS = "of shape [B, P] (or [B, ...], trailing dims are flattened)"


def _check_labels(pred: object, gt: object, ignore: object | None) -> tuple[Tensor, ...]:
    pred = require_tensor("pred", pred, _LABELS)
    gt = require_tensor("gt", gt, _LABELS)
    require_integer("pred", pred, _LABELS)
    require_integer("gt", gt, _LABELS)
    require_batched("pred", pred, f"a tensor {_LABELS}")
    require_same_shape("gt", gt, "pred", pred)
    if gt.device != pred.device:
        raise ValueError(f"gt: expected a tensor on {pred.device} like pred, got {gt.device}")
    if ignore is not None:
        ignore = require_tensor("ignore", ignore, f"of dtype bool {_LABELS}")
        if ignore.dtype != torch.bool:
            raise ValueError(f"ignore: expected a bool tensor like pred, got {describe(ignore)}")
        require_same_shape("ignore", ignore, "pred", pred)
        ignore = ignore.to(pred.device)
    return pred, gt, ignore


def ari(pred: Tensor, gt: Tensor, ignore: Tensor | None = None) -> Tensor:
    """Adjusted Rand index per batch row over the pixels not ignored.

    Matches ``sklearn.metrics.adjusted_rand_score(gt_row[keep], pred_row[keep])``
    (it is symmetric) to float64 rounding, including its degenerate case: when no
    pair of pixels is split by one labeling and joined by the other (identical
    partitions, both a single cluster, both all-distinct, one pixel) the score is 1.0.

    Args:
        pred: Predicted labels (e.g. arg-max slot index), integer ``[B, P]``;
            trailing dims after B are flattened (``[B, H, W]`` works). Any integer
            values; only the partition matters.
        gt: Ground-truth labels, integer, same shape as ``pred``.
        ignore: Optional bool mask, same shape; True pixels are left out.

    Returns:
        Float64 ``[B]``: ARI in [-1, 1] per row, NaN for a row with no pixel left.

    Raises:
        ValueError: On a non-tensor, a non-integer label tensor, a non-bool
            ``ignore``, fewer than 2 dims, or mismatched shapes.
    """
    pred, gt, ignore = _check_labels(pred, gt, ignore)
    batch = pred.shape[0]
    pred = pred.reshape(batch, -1).long()
    gt = gt.reshape(batch, -1).long()
    if ignore is None:
        valid = torch.ones_like(pred, dtype=torch.bool)
    else:
        valid = ~ignore.reshape(batch, -1)
    return ari_rows(pred, gt, valid)


def ari_score(pred: Tensor, gt: Tensor) -> Tensor:
    """ARI over all pixels, background being one ground-truth cluster.

    Args:
        pred: Integer ``[B, P]`` (or ``[B, ...]``) predicted labels.
        gt: Integer ground-truth instance ids, same shape (0 = background).

    Returns:
        Float64 ``[B]`` ARI per row.
    """
    return ari(pred, gt)


def fg_ari_score(pred: Tensor, gt: Tensor) -> Tensor:
    """Foreground ARI: ARI over the pixels whose ground-truth id is not 0.

    Args:
        pred: Integer ``[B, P]`` (or ``[B, ...]``) predicted labels.
        gt: Integer ground-truth instance ids, same shape (0 = background, excluded).

    Returns:
        Float64 ``[B]`` FG-ARI per row; NaN for a row without foreground pixels.
    """
    gt = require_tensor("gt", gt, _LABELS)
    return ari(pred, gt, ignore=gt == 0)


def segmentation_metrics(
    pred_views: Tensor, gt_views: Tensor, input_view: int = 0
) -> dict[str, Tensor]:
    """All segmentation scores of a batch of multi-view scenes.

    Keys (each a float64 ``[B]`` tensor, one value per scene), see
    :data:`SEGMENTATION_KEYS`:

    - ``ari``, ``fg_ari``: ARI / FG-ARI of the input view.
    - ``nv_ari``: mean ARI over the novel views (every view but ``input_view``).
    - ``nv_fg_ari``: mean FG-ARI over the novel views; views without foreground
      (NaN) are skipped (``nanmean``), NaN if none has foreground.
    - ``nv_ari_last``: ARI of the last novel view only (the variant of the uORF
      evaluation code).
    - ``ari_all``, ``fg_ari_all``: ARI* / FG-ARI*, the pixels of all views pooled
      into one labeling per scene (an object must get the same slot in every view).

    ``nv_*`` are NaN when ``V == 1``; ``fg_*`` are NaN when there is no
    foreground pixel to score.

    Args:
        pred_views: Integer ``[B, V, H, W]`` predicted slot index per pixel.
        gt_views: Integer ``[B, V, H, W]`` ground-truth instance ids (0 = background).
        input_view: Index of the view the model was conditioned on, in ``[-V, V)``.

    Returns:
        Dict from the keys above to float64 ``[B]`` tensors.

    Raises:
        ValueError: On wrong dtypes/shapes or an out-of-range ``input_view``.

    Example:
        >>> gt = torch.randint(0, 4, (2, 3, 8, 8))
        >>> m = segmentation_metrics(gt.clone(), gt, input_view=0)
        >>> m["ari_all"]
        tensor([1., 1.], dtype=torch.float64)
    """
    expected = "of shape [B, V, H, W]"
    pred_views = require_tensor("pred_views", pred_views, expected)
    gt_views = require_tensor("gt_views", gt_views, expected)
    require_integer("pred_views", pred_views, expected)
    require_integer("gt_views", gt_views, expected)
    if pred_views.dim() != 4:
        raise ValueError(f"pred_views: expected a tensor {expected}, got {describe(pred_views)}")
    require_same_shape("gt_views", gt_views, "pred_views", pred_views)
    batch, n_views = pred_views.shape[:2]
    if isinstance(input_view, bool) or not isinstance(input_view, int):
        raise ValueError(f"input_view: expected an int, got {type(input_view).__name__}")  # noqa: TRY004
    if not -n_views <= input_view < n_views:
        raise ValueError(
            f"input_view: expected an index in [-{n_views}, {n_views}), got {input_view}"
        )
    input_view %= n_views

    per_view_pred = pred_views.reshape(batch * n_views, -1)
    per_view_gt = gt_views.reshape(batch * n_views, -1)
    view_ari = ari_score(per_view_pred, per_view_gt).view(batch, n_views)
    view_fg_ari = fg_ari_score(per_view_pred, per_view_gt).view(batch, n_views)
    novel = [v for v in range(n_views) if v != input_view]
    if novel:
        nv_ari = view_ari[:, novel].mean(1)
        nv_fg_ari = view_fg_ari[:, novel].nanmean(1)
        nv_ari_last = view_ari[:, novel[-1]]
    else:
        nv_ari = nv_fg_ari = nv_ari_last = torch.full_like(view_ari[:, 0], float("nan"))
    pooled_pred = pred_views.reshape(batch, -1)
    pooled_gt = gt_views.reshape(batch, -1)
    return {
        "ari": view_ari[:, input_view],
        "fg_ari": view_fg_ari[:, input_view],
        "nv_ari": nv_ari,
        "nv_fg_ari": nv_fg_ari,
        "nv_ari_last": nv_ari_last,
        "ari_all": ari_score(pooled_pred, pooled_gt),
        "fg_ari_all": fg_ari_score(pooled_pred, pooled_gt),
    }
