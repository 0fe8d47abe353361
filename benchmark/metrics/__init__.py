"""Benchmark metrics: pure functions from model renders and ground truth to per-scene scores.

Where this sits: the benchmark protocols (``benchmark/``) render a trained model on
a dataset and call these functions; the results go into the JSON reports. No
module here loads models or datasets. Every score is a float64 tensor with one
value per batch row (scene or image); NaN marks a row that cannot be scored
(e.g. FG-ARI without foreground) and protocols aggregate with ``nanmean``.

- :mod:`.segmentation`: ARI, FG-ARI, NV-ARI, ARI*, FG-ARI* (sklearn-exact).
- :mod:`.image`: PSNR, SSIM (skimage-exact).
- :mod:`.lpips`: LPIPS (AlexNet v0.1) from a local weight file, else ``null`` + reason.
- :mod:`.depth`: abs-rel and RMSE depth errors.
"""

from benchmark.metrics.depth import depth_errors
from benchmark.metrics.image import SSIM_WIN_SIZE, psnr, ssim
from benchmark.metrics.lpips import (
    LPIPS_DEFAULT_PATH,
    LPIPS_ENV_VAR,
    LPIPS_MIN_SIDE,
    LPIPSAlex,
    load_lpips_alex,
    lpips_alex,
    lpips_or_null,
    lpips_weight_candidates,
)
from benchmark.metrics.segmentation import (
    SEGMENTATION_KEYS,
    ari,
    ari_score,
    fg_ari_score,
    segmentation_metrics,
)

__all__ = [
    "LPIPS_DEFAULT_PATH",
    "LPIPS_ENV_VAR",
    "LPIPS_MIN_SIDE",
    "SEGMENTATION_KEYS",
    "SSIM_WIN_SIZE",
    "LPIPSAlex",
    "ari",
    "ari_score",
    "depth_errors",
    "fg_ari_score",
    "load_lpips_alex",
    "lpips_alex",
    "lpips_or_null",
    "lpips_weight_candidates",
    "psnr",
    "segmentation_metrics",
    "ssim",
]
