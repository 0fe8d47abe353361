"""Image-quality metrics of novel-view renders: PSNR and SSIM.

Where this sits: the ``nvs`` (and ``ablation`` / ``generalization``) protocols
render each held-out view of a scene with the model and call :func:`psnr` and
:func:`ssim` on the render and the dataset's ground-truth image. Inputs are RGB
batches ``[B, 3, H, W]`` in [0, 1]; values outside are clamped first (a render
may overshoot slightly). All arithmetic is float64; outputs are float64 ``[B]``.

SSIM reproduces ``skimage.metrics.structural_similarity(a, b, channel_axis=-1,
data_range=1.0, gaussian_weights=True, sigma=1.5, use_sample_covariance=False)``:
11x11 Gaussian window (sigma 1.5, truncated at 3.5 sigma), K1 = 0.01, K2 = 0.03,
population covariances, SSIM map averaged per channel after cropping a border of
``(11 - 1) // 2 = 5`` pixels, then averaged over channels. Because the crop equals
the window radius, every kept pixel sees only real image pixels, so a "valid"
convolution gives exactly skimage's numbers whatever its padding mode.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

from benchmark.metrics._checks import describe, require_float, require_same_shape, require_tensor

__all__ = ["SSIM_WIN_SIZE", "psnr", "ssim"]

_SIGMA = 1.5
_TRUNCATE = 3.5  # skimage's SSIM truncation: win_size = 2 * int(3.5 * 1.5 + 0.5) + 1
_RADIUS = int(_TRUNCATE * _SIGMA + 0.5)
#: Side of the SSIM Gaussian window (11); images must be at least this large.
SSIM_WIN_SIZE: int = 2 * _RADIUS + 1
_K1, _K2 = 0.01, 0.03
_EXPECTED = "of shape [B, 3, H, W] with values in [0, 1]"


def _check_images(pred: object, gt: object, min_side: int = 1) -> tuple[Tensor, Tensor]:
    pred = require_tensor("pred", pred, _EXPECTED)
    gt = require_tensor("gt", gt, _EXPECTED)
    require_float("pred", pred, _EXPECTED)
    require_float("gt", gt, _EXPECTED)
    if pred.dim() != 4 or pred.shape[1] != 3:
        raise ValueError(f"pred: expected a tensor {_EXPECTED}, got {describe(pred)}")
    require_same_shape("gt", gt, "pred", pred)
    if min(pred.shape[-2:]) < min_side:
        raise ValueError(f"pred: expected H and W of at least {min_side}, got {tuple(pred.shape)}")
    if gt.device != pred.device:
        raise ValueError(f"gt: expected a tensor on {pred.device} like pred, got {gt.device}")
    f64 = torch.float64
    return pred.to(f64).clamp(0.0, 1.0), gt.to(f64).clamp(0.0, 1.0)


def psnr(pred: Tensor, gt: Tensor) -> Tensor:
    """Peak signal-to-noise ratio per image, data range 1.

    ``PSNR = 10 * log10(1 / MSE)`` with the MSE over all pixels and channels of
    the clamped images; ``inf`` for identical images.

    Args:
        pred: Float ``[B, 3, H, W]`` rendered RGB in [0, 1].
        gt: Float ``[B, 3, H, W]`` ground-truth RGB in [0, 1].

    Returns:
        Float64 ``[B]`` PSNR in dB.

    Raises:
        ValueError: On non-float tensors or shapes other than matching ``[B, 3, H, W]``.

    Example:
        >>> gt = torch.zeros(1, 3, 4, 4)
        >>> psnr(gt + 0.1, gt)  # MSE = 0.01
        tensor([20.0000], dtype=torch.float64)
    """
    pred, gt = _check_images(pred, gt)
    mse = (pred - gt).square().flatten(1).mean(1)
    return -10.0 * torch.log10(mse)


def _gaussian_window(device: torch.device) -> Tensor:
    """Normalised 1-D Gaussian taps, as ``scipy.ndimage`` builds them, float64 ``[11]``."""
    x = torch.arange(-_RADIUS, _RADIUS + 1, dtype=torch.float64, device=device)
    taps = torch.exp(-0.5 / (_SIGMA * _SIGMA) * x * x)
    return taps / taps.sum()


def _filter_valid(x: Tensor, taps: Tensor) -> Tensor:
    """Separable Gaussian filter, 'valid' region only: ``[N, 1, H, W] -> [N, 1, H-10, W-10]``."""
    x = F.conv2d(x, taps.view(1, 1, -1, 1))
    return F.conv2d(x, taps.view(1, 1, 1, -1))


def ssim(pred: Tensor, gt: Tensor) -> Tensor:
    """Structural similarity per image (Gaussian 11x11, sigma 1.5, data range 1).

    Equals ``skimage.metrics.structural_similarity`` with ``channel_axis=-1,
    data_range=1.0, gaussian_weights=True, sigma=1.5,
    use_sample_covariance=False`` on the HWC float64 images (to ~1e-15).

    Args:
        pred: Float ``[B, 3, H, W]`` rendered RGB in [0, 1], ``H, W >= 11``.
        gt: Float ``[B, 3, H, W]`` ground-truth RGB in [0, 1].

    Returns:
        Float64 ``[B]`` mean SSIM (1 for identical images).

    Raises:
        ValueError: On non-float tensors, mismatched shapes, or ``H`` or ``W`` < 11.
    """
    pred, gt = _check_images(pred, gt, min_side=SSIM_WIN_SIZE)
    batch, channels, height, width = pred.shape
    taps = _gaussian_window(pred.device)
    x = pred.reshape(batch * channels, 1, height, width)
    y = gt.reshape(batch * channels, 1, height, width)
    # One filter call over the five stacked moment images.
    stack = torch.cat([x, y, x * x, y * y, x * y], dim=1).reshape(-1, 1, height, width)
    moments = _filter_valid(stack, taps)
    ux, uy, uxx, uyy, uxy = moments.view(batch * channels, 5, *moments.shape[-2:]).unbind(1)
    vx = uxx - ux * ux
    vy = uyy - uy * uy
    vxy = uxy - ux * uy
    c1 = _K1 * _K1  # (K1 * data_range) ** 2 with data_range = 1
    c2 = _K2 * _K2
    num = (2.0 * ux * uy + c1) * (2.0 * vxy + c2)
    den = (ux * ux + uy * uy + c1) * (vx + vy + c2)
    ssim_map = num / den
    # Mean per channel (crop already done by the valid filter), then over channels.
    return ssim_map.view(batch, channels, -1).mean(2).mean(1)
