"""How report values read to a person: one formatting function per metric kind.

Where this sits: the terminal leaderboard (:mod:`benchmark.leaderboard`), the HTML
pages (:mod:`benchmark.html`) and the figures (:mod:`benchmark.figures`) all format
numbers, metric names, table ids and null reasons through this module, so a value
reads the same everywhere. ``report.json`` is untouched: it keeps the stored values
(ARI family in percent, see :data:`benchmark.schema.METRIC_UNITS`).

Conventions (the paper's):

- ARI family (ARI, FG-ARI, NV-ARI, ARI*, FG-ARI*, their scene-shuffle controls and
  chance baselines): the 0-100 scale, one decimal (``92.0``).
- PSNR: one decimal, in dB (``37.2 dB``).
- SSIM, LPIPS: three decimals (``0.970``).
- Times carry their unit, chosen by size (``850 ms``, ``204 s``, ``17.5 min``);
  memory too (``4.6 GB``, ``512 MiB``); ratios end in ``x``.
- A missing value (``null``) is an em dash; its reason reads as words
  (:func:`reason_text`: ``paper_na`` -> "not in the paper").
"""

from __future__ import annotations

import math
import re
from typing import Any

__all__ = [
    "ARI_FAMILY",
    "LEGEND",
    "METRIC_LABELS",
    "NULL",
    "TABLE_TITLES",
    "fmt_ari",
    "fmt_count",
    "fmt_error",
    "fmt_fraction",
    "fmt_memory",
    "fmt_metric",
    "fmt_plain",
    "fmt_psnr",
    "fmt_rate",
    "fmt_ratio",
    "fmt_seconds",
    "fmt_similarity",
    "metric_kind",
    "metric_label",
    "reason_text",
    "table_description",
    "table_ref",
    "table_title",
]

#: How a null value is shown.
NULL = "\u2014"

#: Metrics on the paper's 0-100 ARI scale (stored in percent in report.json).
ARI_FAMILY = frozenset(
    {
        "ari",
        "fg_ari",
        "nv_ari",
        "nv_fg_ari",
        "nv_ari_last",
        "ari_all",
        "fg_ari_all",
        "ari_shuffled",
        "fg_ari_shuffled",
        "fg_ari_gain",
        "chance_fg_ari",
    }
)

#: One sentence on the units, printed with the leaderboard and on every page.
LEGEND = (
    "ARI-family scores (ARI, FG-ARI, NV-ARI, ARI*, FG-ARI*, shuffled and chance variants) "
    "are on the paper's 0-100 scale."
)

#: Column names as a reader knows them (the paper's where it has one).
METRIC_LABELS: dict[str, str] = {
    "ari": "ARI",
    "fg_ari": "FG-ARI",
    "nv_ari": "NV-ARI",
    "nv_fg_ari": "NV-FG-ARI",
    "nv_ari_last": "NV-ARI last view",
    "ari_all": "ARI*",
    "fg_ari_all": "FG-ARI*",
    "ari_shuffled": "ARI shuffled",
    "fg_ari_shuffled": "FG-ARI shuffled",
    "fg_ari_gain": "FG-ARI gain",
    "chance_fg_ari": "best chance FG-ARI",
    "psnr": "PSNR",
    "ssim": "SSIM",
    "lpips": "LPIPS",
    "depth_abs_rel": "depth AbsRel",
    "depth_rmse": "depth RMSE",
    "memory_gb": "memory",
    "epoch_time_s": "epoch time",
    "steps_per_s": "steps/s",
    "step_time_s": "step time",
    "peak_memory_mb": "peak memory",
    "render_s_per_view": "render/view",
    "train_memory_mb": "training memory",
    "step_time_ratio": "step time ratio",
    "memory_ratio": "memory ratio",
    "train_memory_ratio": "training memory ratio",
    "tensor_peak_mb": "tensor peak",
    "tensor_memory_ratio": "tensor memory ratio",
    "images_per_s": "images/s",
    "s_per_view": "time/view",
    "overhead_ratio": "overhead",
    "scaling_speedup": "speed-up",
    "baseline_speedup": "speed-up vs script",
    "baseline_s_per_view": "script time/view",
    "baseline_psnr": "script PSNR",
    "max_abs_err_rgb": "max err rgb",
    "max_abs_err_depth": "max err depth",
    "max_rel_err_depth": "max rel err depth",
    "max_abs_err_acc": "max err acc",
    "nonfinite_count": "non-finite",
    "max_abs_err_m": "max err masks",
    "max_rel_err": "max rel err",
    "value": "value",
    "reference_value": "reference",
    "abs_err": "abs err",
    "diverged_at_step": "diverged at step",
    "checkpoint_step": "checkpoint step",
    "error": "error",
    "time_s": "time",
    "speedup": "speed-up",
    "rgb_max_err": "rgb max err",
    "rgb_mean_err": "rgb mean err",
    "depth_mean_err": "depth mean err",
    "slot_probs_max_err": "mask max err",
    "kept_pairs": "kept pairs",
    "labels_changed": "labels changed",
}

#: Table id (the paper's LaTeX label, or the benchmark's own id) -> title. Table numbers
#: follow the paper's numbering (``\\caption`` order in svorf_neurips2023.tex; the
#: appendix continues it: Table 9 is the upsampling architecture).
TABLE_TITLES: dict[str, str] = {
    "tab:seg": "Segmentation (Table 1)",
    "tab:seg_osrt": "CLEVR-3D segmentation (Table 2a)",
    "tab:novel_osrt": "CLEVR-3D novel view synthesis (Table 2b)",
    "tab:nvs": "Novel view synthesis (Table 3)",
    "tab:msn": "MultiShapeNet (Table 4)",
    "tab:ablation": "Ablations (Table 5)",
    "tab:ab_apparance": "Held-out appearance (Table 6)",
    "tab:ab_num": "Spatial arrangements, packed CLEVR-11 (Table 7)",
    "text:rgb_color": "Grayscale test images (Section 4.5, text)",
    "tab:time": "Memory and training time (Table 8)",
    "tab:supp_ablation": "Architecture ablations (Table 10, appendix)",
    "speed": "Training and rendering speed at this scale",
    "speed_inference": "Inference speed",
    "speed_vs_uorf": "sVORF vs the uORF-style configuration",
    "speed_generator": "Scene generator speed",
    "stability": "Stability: volume renderer",
    "stability_compose": "Stability: slot masks and composition",
    "stability_loss": "Stability: connectivity loss",
    "stability_metrics": "Stability: metrics vs reference implementations",
    "stability_training": "Stability: training NaN guard",
}

#: Null-reason codes (the part before ':' or ' (') -> words.
REASON_WORDS: dict[str, str] = {
    "paper_na": "not in the paper",
    "not_reported_in_paper": "not reported in the paper",
    "lpips_unavailable": "LPIPS weights not available",
    "needs_two_scenes": "needs two test scenes",
    "no_finite_value": "no finite value",
    "non_finite": "not finite (NaN or infinity)",
    "non_finite_error": "not finite",
    "not_computed": "not computed",
    "not_measured": "not measured",
    "failed": "row failed",
    "not_trained": "model not trained in this run",
    "dataset_unavailable": "dataset unavailable",
}

_TIME = {
    "epoch_time_s",
    "step_time_s",
    "render_s_per_view",
    "s_per_view",
    "baseline_s_per_view",
    "time_s",
}
_MEMORY = {"memory_gb": "GB", "peak_memory_mb": "MiB", "train_memory_mb": "MiB",
           "tensor_peak_mb": "MiB"}  # fmt: skip
_RATIO = {
    "step_time_ratio",
    "memory_ratio",
    "train_memory_ratio",
    "tensor_memory_ratio",
    "overhead_ratio",
    "scaling_speedup",
    "baseline_speedup",
    "speedup",
}
_RATE = {"steps_per_s", "images_per_s"}
_COUNT = {"nonfinite_count", "diverged_at_step", "checkpoint_step"}
_ERROR = {
    "max_abs_err_rgb",
    "max_abs_err_depth",
    "max_rel_err_depth",
    "max_abs_err_acc",
    "max_abs_err_m",
    "max_rel_err",
    "abs_err",
    "error",
    "rgb_max_err",
    "rgb_mean_err",
    "depth_mean_err",
    "slot_probs_max_err",
}
_FRACTION = {"kept_pairs", "labels_changed", "depth_abs_rel", "depth_rmse"}


def metric_kind(metric: str) -> str:
    """The formatting kind of a metric: ``ari``, ``psnr``, ``similarity``, ``time``,
    ``memory``, ``ratio``, ``rate``, ``count``, ``error``, ``fraction`` or ``plain``."""
    if metric in ARI_FAMILY:
        return "ari"
    if metric in ("psnr", "baseline_psnr"):
        return "psnr"
    if metric in ("ssim", "lpips"):
        return "similarity"
    if metric in _TIME:
        return "time"
    if metric in _MEMORY:
        return "memory"
    if metric in _RATIO:
        return "ratio"
    if metric in _RATE:
        return "rate"
    if metric in _COUNT or metric.startswith("n_"):
        return "count"
    if metric in _ERROR:
        return "error"
    if metric in _FRACTION:
        return "fraction"
    return "plain"


def _sig(v: float, digits: int = 3) -> str:
    """``v`` to ``digits`` significant digits, never in exponent notation."""
    if v == 0:
        return "0"
    decimals = max(0, digits - 1 - math.floor(math.log10(abs(v))))
    text = f"{v:.{decimals}f}"
    return "0" if float(text) == 0 else text


def _fixed(v: float, decimals: int) -> str:
    text = f"{v:.{decimals}f}"
    return text[1:] if text.startswith("-") and float(text) == 0 else text  # no "-0.0"


def fmt_ari(v: float) -> str:
    """ARI family, stored in percent: the paper's 0-100 scale, one decimal (``92.0``)."""
    return _fixed(v, 1)


def fmt_psnr(v: float, unit: bool = True) -> str:
    """PSNR: one decimal, dB (``37.2 dB``)."""
    return _fixed(v, 1) + (" dB" if unit else "")


def fmt_similarity(v: float) -> str:
    """SSIM / LPIPS: three decimals (``0.970``)."""
    return _fixed(v, 3)


def fmt_seconds(v: float, unit: bool = True) -> str:
    """A duration with its unit, chosen by size: ``850 ms``, ``12.3 s``, ``204 s``,
    ``17.5 min``, ``3.1 h`` (three significant digits below 1000 s). With
    ``unit=False``: seconds, three significant digits, no unit."""
    if not unit:
        return _sig(v)
    a = abs(v)
    if a == 0:
        return "0 s"
    if a < 1e-3:
        return f"{_sig(v * 1e6)} \u00b5s"
    if a < 1:
        return f"{_sig(v * 1e3)} ms"
    if a < 1000:
        return f"{_sig(v)} s"
    if a < 7200:
        return f"{v / 60:.1f} min"
    return f"{v / 3600:.1f} h"


def fmt_memory(v: float, unit: str = "GB") -> str:
    """Memory in its stored unit (``GB`` or ``MiB``): ``4.6 GB``, ``0.39 GB``, ``512 MiB``."""
    a = abs(v)
    text = _fixed(v, 0 if a >= 100 else 1 if a >= 1 else 2)
    return f"{text} {unit}" if unit else text


def fmt_ratio(v: float, digits: int = 2) -> str:
    """A ratio or speed-up: ``2.50x`` (``digits`` decimals)."""
    return f"{_fixed(v, digits)}x"


def fmt_rate(v: float) -> str:
    """Things per second: ``12.3/s``."""
    return f"{_sig(v)}/s"


def fmt_count(v: float) -> str:
    """A count or a step number: ``3``."""
    return str(round(v))


def fmt_error(v: float) -> str:
    """A numerical error: ``2.0e-07`` (exactly 0 as ``0``)."""
    return "0" if v == 0 else f"{v:.1e}"


def fmt_fraction(v: float) -> str:
    """A fraction or a relative error: three decimals (``0.125``)."""
    return _fixed(v, 3)


def fmt_plain(v: float) -> str:
    """Anything else: four significant digits."""
    return f"{v:.4g}"


def fmt_metric(metric: str, v: Any, unit: bool = True) -> str:
    """``v`` of ``metric`` as a person reads it (null -> an em dash).

    Args:
        metric: the metric name (a key of :data:`benchmark.schema.METRIC_UNITS`, or
            ``chance_fg_ari`` of a verdict).
        v: the stored value (number, None, bool or text).
        unit: append the unit where the kind has one (dB, s, GB...); a table whose
            header already names the unit can leave it out.
    """
    if v is None:
        return NULL
    if isinstance(v, bool):
        return "yes" if v else "no"
    if not isinstance(v, (int, float)):
        return str(v)
    v = float(v)
    if not math.isfinite(v):
        return str(v)
    kind = metric_kind(metric)
    if kind == "ari":
        return fmt_ari(v)
    if kind == "psnr":
        return fmt_psnr(v, unit)
    if kind == "similarity":
        return fmt_similarity(v)
    if kind == "time":
        return fmt_seconds(v, unit)
    if kind == "memory":
        return fmt_memory(v, _MEMORY[metric] if unit else "")
    if kind == "ratio":
        return fmt_ratio(v)
    if kind == "rate":
        return fmt_rate(v) if unit else _sig(v)
    if kind == "count":
        return fmt_count(v)
    if kind == "error":
        return fmt_error(v)
    if kind == "fraction":
        return fmt_fraction(v)
    return fmt_plain(v)


def metric_label(metric: str) -> str:
    """A metric's column name (``fg_ari`` -> ``FG-ARI``)."""
    return METRIC_LABELS.get(metric, metric.replace("_", " "))


def table_title(table: str) -> str:
    """A table's title (``tab:ab_apparance`` -> ``Held-out appearance (Table 6)``); ids
    that are already words (``tradeoff: init weights``) are returned as they are."""
    return TABLE_TITLES.get(table, table)


def table_ref(table: str) -> str:
    """The short reference of a table (``Table 6``, ``Section 4.5, text``), or its title
    when it is not one of the paper's."""
    m = re.search(r"\(((?:Table|Section) [^)]*)\)$", table_title(table))
    return m.group(1) if m else table_title(table)


def table_description(table: str) -> str:
    """The paper table's caption without the table number the title already gives
    (empty for the benchmark's own tables)."""
    from benchmark.paper_numbers import PAPER_TABLES

    caption = PAPER_TABLES.get(table, {}).get("caption", "")
    return re.sub(r"\s*\(Table \d+[a-z]?\)", "", caption)


def reason_text(reason: str) -> str:
    """A null reason as words: the leading code becomes a phrase and the detail stays
    (``paper_na`` -> "not in the paper"; ``failed: boom`` -> "row failed: boom")."""
    m = re.match(r"^([a-z][a-z0-9_]*)(.*)$", reason or "", re.DOTALL)
    if not m or m.group(1) not in REASON_WORDS:
        return reason
    return REASON_WORDS[m.group(1)] + m.group(2)
