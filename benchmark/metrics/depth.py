"""Depth errors of rendered depth against the dataset's ground-truth depth.

Where this sits: the ``nvs`` / ``ablation`` protocols render the expected ray
termination depth of each view with the model and call :func:`depth_errors`
with the dataset's ground-truth depth of the same convention (both planar
``depth_z`` or both distance along the ray, in world units: this module does not
convert). Pixels count only where the ground truth is finite and > 0 (background
and sky are stored as 0 or inf) and the caller's mask is True.
"""

from __future__ import annotations

import torch
from torch import Tensor

from benchmark.metrics._checks import (
    describe,
    require_batched,
    require_float,
    require_same_shape,
    require_tensor,
)

__all__ = ["depth_errors"]

_EXPECTED = "of shape [B, H, W] (or [B, ...])"


def depth_errors(
    pred_depth: Tensor, gt_depth: Tensor, valid_mask: Tensor | None = None
) -> dict[str, Tensor]:
    """Absolute relative error and RMSE per image over the valid pixels.

    ``abs_rel = mean(|pred - gt| / gt)`` and ``rmse = sqrt(mean((pred - gt)^2))``
    over pixels with ``isfinite(gt) & (gt > 0) & valid_mask``; both NaN for an
    image without a valid pixel (aggregate with ``nanmean``).

    Args:
        pred_depth: Float ``[B, H, W]`` (any ``[B, ...]``) rendered depth, world units.
        gt_depth: Float ground-truth depth, same shape and convention.
        valid_mask: Optional bool mask, same shape (e.g. foreground only).

    Returns:
        ``{"abs_rel": Tensor[B], "rmse": Tensor[B]}``, float64.

    Raises:
        ValueError: On non-float depths, a non-bool mask, or mismatched shapes.

    Example:
        >>> gt = torch.full((1, 2, 2), 2.0)
        >>> depth_errors(gt + 0.5, gt)["abs_rel"]
        tensor([0.2500], dtype=torch.float64)
    """
    pred_depth = require_tensor("pred_depth", pred_depth, _EXPECTED)
    gt_depth = require_tensor("gt_depth", gt_depth, _EXPECTED)
    require_float("pred_depth", pred_depth, _EXPECTED)
    require_float("gt_depth", gt_depth, _EXPECTED)
    require_batched("pred_depth", pred_depth, f"a tensor {_EXPECTED}")
    require_same_shape("gt_depth", gt_depth, "pred_depth", pred_depth)
    batch = pred_depth.shape[0]
    pred = pred_depth.to(torch.float64).reshape(batch, -1)
    gt = gt_depth.to(device=pred.device, dtype=torch.float64).reshape(batch, -1)
    valid = torch.isfinite(gt) & (gt > 0)
    if valid_mask is not None:
        valid_mask = require_tensor("valid_mask", valid_mask, f"of dtype bool {_EXPECTED}")
        if valid_mask.dtype != torch.bool:
            raise ValueError(
                f"valid_mask: expected a bool tensor like pred_depth, got {describe(valid_mask)}"
            )
        require_same_shape("valid_mask", valid_mask, "pred_depth", pred_depth)
        valid = valid & valid_mask.to(pred.device).reshape(batch, -1)
    count = valid.sum(1).to(torch.float64)
    # Zero out invalid pixels before the arithmetic so inf/NaN there cannot leak in.
    safe_gt = torch.where(valid, gt, torch.ones_like(gt))
    diff = torch.where(valid, pred - safe_gt, torch.zeros_like(pred))
    abs_rel = (diff.abs() / safe_gt).sum(1) / count
    rmse = (diff.square().sum(1) / count).sqrt()
    nan = torch.full_like(count, float("nan"))
    return {
        "abs_rel": torch.where(count > 0, abs_rel, nan),
        "rmse": torch.where(count > 0, rmse, nan),
    }
