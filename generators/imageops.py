"""Pixel conversions between the render and the files (pure numpy).

Data flow: ``blender_backend`` returns the scene-linear Combined pass ->
:func:`linear_to_srgb8` -> the RGB PNG; ``clevr567-gray`` applies
:func:`grayscale_rec601` to those 8-bit sRGB values.
"""

from __future__ import annotations

import numpy as np

from scenefmt import LUMA_REC601

GRAYSCALE_FORMULA = (
    "Y = 0.299 R + 0.587 G + 0.114 B (Rec.601 luma) on the 8-bit sRGB values, "
    "rounded half to even, stored in all 3 channels"
)


def srgb_oetf(x: np.ndarray) -> np.ndarray:
    """The standard sRGB OETF (IEC 61966-2-1), the curve of Blender's 'Standard' view.

    ``12.92 x`` for ``x <= 0.0031308``, else ``1.055 x^(1/2.4) - 0.055``.
    """
    x = np.asarray(x, dtype=np.float64)
    return np.where(
        x <= 0.0031308, 12.92 * x, 1.055 * np.power(np.maximum(x, 0.0031308), 1 / 2.4) - 0.055
    )


def linear_to_srgb8(rgb_linear: np.ndarray) -> np.ndarray:
    """Scene-linear float RGB -> 8-bit sRGB: ``round(255 * oetf(clip(x, 0, 1)))``.

    No dithering (unlike Blender's own 8-bit save), so the conversion is deterministic.

    Args:
        rgb_linear: float [H, W, 3].

    Returns:
        uint8 [H, W, 3].
    """
    x = np.clip(np.nan_to_num(np.asarray(rgb_linear, dtype=np.float64), nan=0.0), 0.0, 1.0)
    return np.rint(srgb_oetf(x) * 255.0).astype(np.uint8)


def grayscale_rec601(rgb8: np.ndarray) -> np.ndarray:
    """8-bit sRGB RGB -> 3 equal channels of Rec.601 luma (see :data:`GRAYSCALE_FORMULA`).

    Args:
        rgb8: uint8 [H, W, 3].

    Returns:
        uint8 [H, W, 3] with R == G == B.
    """
    rgb8 = np.asarray(rgb8)
    if rgb8.dtype != np.uint8 or rgb8.ndim != 3 or rgb8.shape[2] != 3:
        raise ValueError(f"rgb8 must be uint8 [H, W, 3], got {rgb8.dtype} {rgb8.shape}")
    y = rgb8.astype(np.float64) @ np.array(LUMA_REC601)
    y8 = np.clip(np.rint(y), 0, 255).astype(np.uint8)
    return np.repeat(y8[..., None], 3, axis=2)
