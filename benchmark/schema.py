"""The versioned JSON schema of benchmark reports and its hand-written validator.

Where this sits: every protocol builds a report dict and calls
:func:`validate_report` before writing it (``benchmark.report.write_report``);
the leaderboard validates the reports it merges. No ``jsonschema`` dependency:
the rules are plain Python so the error messages can name the exact field.

Report layout (``schema_version`` ``REPORT_SCHEMA_VERSION``)::

    {
      "schema_version": "1.0", "kind": "svorf-benchmark-report",
      "protocol": "segmentation|nvs|ablation|generalization|speed|tradeoff|stability|editing",
      "scale": "smoke|cpu|paper", "status": "complete|partial",
      "created_utc": "2025-01-01T00:00:00Z",
      "git": {"commit": str|null, "dirty": bool|null, "reason": str|null},
      "hardware": {"cpu_model", "cpu_cores", "torch_version", "device", "gpu_name",
                   "python_version", "platform"},
      "seeds": {"data": int, "train": int, "eval": int},
      "scale_settings": {...},                # dataset sizes, resolution, steps
      "datasets": [{"name", "preset", "split", "path", "fingerprint", "n_scenes",
                    "n_views", "resolution", "source"}],
      "models": [{"run_key", "variant", "train_dataset", "model_config",
                  "train_config", "seed", "reused", "train_wall_s"}],
      "wall_time_s": {"data", "training", "evaluation", "total"},
      "rows": [{"id", "table", "model", "dataset", "variant",
                "source": "paper|measured|baseline",
                "metrics": {name: number|null}, "null_reasons": {name: str}, ...}],
      "verdicts": [{"dataset", "model", "decomposes": bool|null, "message"}],
                                              # + "fg_ari", "chance_fg_ari", "fg_ari_shuffled"
      "notes": [str], "figures": [str], "units": {metric: str}
    }

Scales of stored values: metrics are stored in the units of :data:`METRIC_UNITS` (copied
into each report's ``units``). The ARI family (``ari``, ``fg_ari``, ``nv_ari``,
``nv_fg_ari``, ``nv_ari_last``, ``ari_all``, ``fg_ari_all``, ``ari_shuffled``,
``fg_ari_shuffled``, ``fg_ari_gain``, and a verdict's ``fg_ari`` / ``chance_fg_ari`` /
``fg_ari_shuffled``) is stored in percent, the paper's 0-100 scale. Two places keep a
0-1 ARI on purpose: the ``value`` / ``reference_value`` of ``stability_metrics`` rows
(ARI in [-1, 1], compared with sklearn), and the ``held_out`` points of a ``tradeoff``
training curve (copied from the run's ``eval.jsonl``). Pages, figures and the printed
leaderboard show the ARI-family metrics on the 0-100 scale (:mod:`benchmark.display`);
the stored values are never rescaled.

Rules beyond types: no NaN or infinity anywhere (a metric that cannot be
computed is ``null`` and its reason is in ``null_reasons``); metric names come
from :data:`METRIC_UNITS`; paper rows must equal the transcription in
:mod:`benchmark.paper_numbers`; measured and baseline rows carry ``n_scenes`` (or ``n_cases``), and a row of 0
scenes has only null metrics.
"""

from __future__ import annotations

import math
import re
from typing import Any

from benchmark.paper_numbers import PAPER_TABLES
from svorf.registry import SCALE_NAMES

__all__ = [
    "METRIC_UNITS",
    "PROTOCOLS",
    "REPORT_KIND",
    "REPORT_SCHEMA_VERSION",
    "ROW_SOURCES",
    "SCALES",
    "SchemaError",
    "check_report",
    "validate_report",
]

REPORT_SCHEMA_VERSION = "1.0"
REPORT_KIND = "svorf-benchmark-report"
PROTOCOLS = (
    "segmentation", "nvs", "ablation", "generalization", "speed", "tradeoff", "stability",
    "editing",
)  # fmt: skip
#: Scale names (svorf's registry, ``svorf.registry.SCALE_NAMES``).
SCALES: tuple[str, ...] = SCALE_NAMES
ROW_SOURCES = ("paper", "measured", "baseline")
DATA_SOURCES = ("generator", "synthetic", "existing")

#: Every metric a row may carry, with its unit (ARI family in percent, as the paper prints).
METRIC_UNITS: dict[str, str] = {
    "ari": "percent",
    "fg_ari": "percent",
    "nv_ari": "percent",
    "nv_fg_ari": "percent",
    "nv_ari_last": "percent",
    "ari_all": "percent",
    "fg_ari_all": "percent",
    # scene-shuffle control: the input view rendered with another test scene's slots
    "ari_shuffled": "percent (input-view ARI with the slots of another test scene)",
    "fg_ari_shuffled": "percent (input-view FG-ARI with the slots of another test scene)",
    "fg_ari_gain": "percentage points (fg_ari - fg_ari_shuffled)",
    "psnr": "dB",
    "ssim": "unitless [0,1]",
    "lpips": "unitless (lower is better)",
    "depth_abs_rel": "unitless",
    "depth_rmse": "world units",
    "memory_gb": "GB",
    "epoch_time_s": "s",
    "steps_per_s": "1/s",
    "step_time_s": "s",
    "peak_memory_mb": "MiB",
    "render_s_per_view": "s",
    # speed: sVORF against the uORF-style configuration, generator, inference
    "train_memory_mb": "MiB (peak memory minus the memory in use at the first training step)",
    "step_time_ratio": "ratio (uORF-style median step time / sVORF's; > 1 = sVORF faster)",
    "memory_ratio": "ratio (uORF-style peak memory / sVORF's; > 1 = sVORF smaller)",
    "train_memory_ratio": "ratio (uORF-style train_memory_mb / sVORF's; > 1 = sVORF smaller)",
    "tensor_peak_mb": "MiB (peak live tensor bytes during training: CUDA max_memory_allocated, "
    "CPU allocator events of torch.profiler)",
    "tensor_memory_ratio": "ratio (uORF-style tensor_peak_mb / sVORF's; > 1 = sVORF smaller)",
    "images_per_s": "1/s (rendered images per second)",
    "s_per_view": "s (wall seconds per rendered view)",
    "overhead_ratio": "ratio (generate s/view / bare Cycles s/view, same views and settings)",
    "scaling_speedup": "ratio (first worker count's wall / this one's; > 1 = faster)",
    "baseline_speedup": "ratio (straightforward bpy script's wall / generate's, same scenes; "
    "> 1 = generate faster)",
    "baseline_s_per_view": "s (the straightforward bpy script's wall seconds per view)",
    "baseline_psnr": "dB (the straightforward bpy script's PSNR against the same reference)",
    "max_abs_err_rgb": "unitless",
    "max_abs_err_depth": "world units",
    "max_rel_err_depth": "unitless (relative to the largest sample distance)",
    "max_abs_err_acc": "unitless",
    "nonfinite_count": "count",
    # stability: composition, losses, metrics and the NaN guard
    "max_abs_err_m": "unitless [0,1] (slot masks, max |diff| from the float64 reference)",
    "max_rel_err": "unitless (|value - float64 reference| / max(1, |reference|))",
    "value": "the row's metric (ARI / FG-ARI in [-1, 1], PSNR in dB, SSIM unitless)",
    "reference_value": "the same metric from sklearn / scikit-image",
    "abs_err": "|value - reference_value|",
    "diverged_at_step": "step (the step the NaN guard named)",
    "checkpoint_step": "step (of the checkpoint left on disk)",
    "error": "unitless",
    "time_s": "s",
    # tradeoff: a speed knob's step time and render error against the knob-free model
    "speedup": "ratio (knob-free median step time / this one; > 1 = faster)",
    "rgb_max_err": "colour units [0,1] (max |diff|)",
    "rgb_mean_err": "colour units [0,1] (mean |diff|)",
    "depth_mean_err": "world units (mean |diff|)",
    "slot_probs_max_err": "unitless [0,1] (max |diff|)",
    "kept_pairs": "fraction of (point, slot) field evaluations",
    # tradeoff render curve: label map against the default render
    "labels_changed": "fraction of pixels whose arg-max slot differs from the default render",
}

_TOP_FIELDS: dict[str, type | tuple[type, ...]] = {
    "schema_version": str,
    "kind": str,
    "protocol": str,
    "scale": str,
    "status": str,
    "created_utc": str,
    "git": dict,
    "hardware": dict,
    "seeds": dict,
    "scale_settings": dict,
    "datasets": list,
    "models": list,
    "wall_time_s": dict,
    "rows": list,
    "verdicts": list,
    "notes": list,
    "figures": list,
    "units": dict,
}
_HARDWARE_FIELDS = {
    "cpu_model": str,
    "cpu_cores": int,
    "torch_version": str,
    "device": str,
    "gpu_name": (str, type(None)),
    "python_version": str,
    "platform": str,
}
_DATASET_FIELDS = {
    "name": str,
    "preset": str,
    "split": str,
    "path": str,
    "fingerprint": str,
    "n_scenes": int,
    "n_views": int,
    "resolution": int,
    "source": str,
}
_MODEL_FIELDS = {
    "run_key": str,
    "variant": str,
    "train_dataset": str,
    "model_config": dict,
    "train_config": dict,
    "seed": int,
    "reused": bool,
    "train_wall_s": (int, float),
}
_ROW_FIELDS = {
    "id": str,
    "table": str,
    "model": str,
    "dataset": str,
    "source": str,
    "metrics": dict,
    "null_reasons": dict,
}
_WALL_FIELDS = ("data", "training", "evaluation", "total")
_FINGERPRINT_RE = re.compile(r"^[0-9a-f]{16,64}$")
_COMMIT_RE = re.compile(r"^[0-9a-f]{40}$")


class SchemaError(ValueError):
    """A report breaks the schema; ``problems`` lists every violation found."""

    def __init__(self, problems: list[str]) -> None:
        self.problems = list(problems)
        shown = "; ".join(self.problems[:8])
        more = f" (+{len(self.problems) - 8} more)" if len(self.problems) > 8 else ""
        super().__init__(f"report breaks schema {REPORT_SCHEMA_VERSION}: {shown}{more}")


def _type_name(t: type | tuple[type, ...]) -> str:
    if isinstance(t, tuple):
        return "|".join("null" if x is type(None) else x.__name__ for x in t)
    return t.__name__


def _is_type(value: Any, t: type | tuple[type, ...]) -> bool:
    types = t if isinstance(t, tuple) else (t,)
    if isinstance(value, bool) and bool not in types:
        return False  # bool is an int subclass; never accept it for a number
    if float in types and isinstance(value, int) and not isinstance(value, bool):
        return True
    return isinstance(value, types)


def _fields(obj: Any, spec: dict[str, Any], where: str, problems: list[str]) -> bool:
    if not isinstance(obj, dict):
        problems.append(f"{where}: expected an object, got {type(obj).__name__}")
        return False
    for name, t in spec.items():
        if name not in obj:
            problems.append(f"{where}.{name}: missing")
        elif not _is_type(obj[name], t):
            problems.append(
                f"{where}.{name}: expected {_type_name(t)}, got {type(obj[name]).__name__}"
            )
    return True


def _non_finite(obj: Any, where: str, problems: list[str]) -> None:
    """Report every NaN/inf float anywhere in the tree (JSON has no NaN)."""
    if isinstance(obj, float):
        if not math.isfinite(obj):
            problems.append(f"{where}: {obj!r} is not allowed (write null plus a reason)")
    elif isinstance(obj, dict):
        for k, v in obj.items():
            if not isinstance(k, str):
                problems.append(f"{where}: key {k!r} is not a string")
            _non_finite(v, f"{where}.{k}", problems)
    elif isinstance(obj, (list, tuple)):
        for i, v in enumerate(obj):
            _non_finite(v, f"{where}[{i}]", problems)
    elif obj is not None and not isinstance(obj, (str, int, bool)):
        problems.append(f"{where}: {type(obj).__name__} is not a JSON value")


def _check_row(row: Any, where: str, problems: list[str]) -> None:
    if not _fields(row, _ROW_FIELDS, where, problems):
        return
    source = row.get("source")
    if source not in ROW_SOURCES:
        problems.append(f"{where}.source: expected one of {ROW_SOURCES}, got {source!r}")
    metrics = row.get("metrics")
    reasons = row.get("null_reasons")
    if not isinstance(metrics, dict) or not isinstance(reasons, dict):
        return
    if not metrics:
        problems.append(f"{where}.metrics: empty")
    for name, value in metrics.items():
        if name not in METRIC_UNITS:
            problems.append(
                f"{where}.metrics.{name}: unknown metric (known: {sorted(METRIC_UNITS)})"
            )
        if value is None:
            reason = reasons.get(name)
            if not isinstance(reason, str) or not reason:
                problems.append(f"{where}.metrics.{name}: null without a reason in null_reasons")
        elif not _is_type(value, float):
            problems.append(
                f"{where}.metrics.{name}: expected number|null, got {type(value).__name__}"
            )
    for name in reasons:
        if name not in metrics:
            problems.append(f"{where}.null_reasons.{name}: no such metric in the row")
        elif metrics[name] is not None:
            problems.append(f"{where}.null_reasons.{name}: metric is not null")
    if source == "paper":
        table = row.get("table")
        if table not in PAPER_TABLES:
            problems.append(f"{where}.table: {table!r} is not a paper table id")
            return
        match = [
            r
            for r in PAPER_TABLES[table]["rows"]
            if r["model"] == row.get("model") and r["dataset"] == row.get("dataset")
        ]
        if not match:
            problems.append(
                f"{where}: paper row {row.get('model')!r}/{row.get('dataset')!r} is not in {table}"
            )
        elif match[0]["metrics"] != metrics:
            problems.append(f"{where}.metrics: differ from benchmark.paper_numbers[{table!r}]")
    elif source in ("measured", "baseline"):
        # How many scenes (or stress cases, or timed steps) the values summarise.
        key = next((k for k in ("n_scenes", "n_cases") if k in row), "n_scenes")
        n = row.get(key)
        if not _is_type(n, int) or n < 0:
            problems.append(f"{where}.{key}: expected an int >= 0 for a {source} row, got {n!r}")
        elif n == 0 and any(v is not None for v in metrics.values()):
            problems.append(f"{where}: {key} is 0 but some metrics are not null")


def check_report(report: Any) -> list[str]:
    """Every schema violation of ``report`` (empty list when it is valid).

    Args:
        report: A report dict as written to ``report.json``.

    Returns:
        Human-readable problems, each starting with the JSON path it concerns.
    """
    problems: list[str] = []
    if not _fields(report, _TOP_FIELDS, "report", problems):
        return problems
    if report.get("schema_version") != REPORT_SCHEMA_VERSION:
        problems.append(
            f"report.schema_version: expected {REPORT_SCHEMA_VERSION!r}, "
            f"got {report.get('schema_version')!r}"
        )
    if report.get("kind") != REPORT_KIND:
        problems.append(f"report.kind: expected {REPORT_KIND!r}, got {report.get('kind')!r}")
    if report.get("protocol") not in PROTOCOLS:
        problems.append(
            f"report.protocol: expected one of {PROTOCOLS}, got {report.get('protocol')!r}"
        )
    if report.get("scale") not in SCALES:
        problems.append(f"report.scale: expected one of {SCALES}, got {report.get('scale')!r}")
    if report.get("status") not in ("complete", "partial"):
        problems.append(f"report.status: expected complete|partial, got {report.get('status')!r}")

    git = report.get("git")
    if isinstance(git, dict):
        _fields(
            git, {"commit": (str, type(None)), "dirty": (bool, type(None))}, "report.git", problems
        )
        commit = git.get("commit")
        if isinstance(commit, str) and not _COMMIT_RE.match(commit):
            problems.append(f"report.git.commit: expected 40 hex digits, got {commit!r}")
        if commit is None and not git.get("reason"):
            problems.append("report.git.reason: required when commit is null")
    if isinstance(report.get("hardware"), dict):
        _fields(report["hardware"], _HARDWARE_FIELDS, "report.hardware", problems)
    seeds = report.get("seeds")
    if isinstance(seeds, dict):
        _fields(seeds, {"data": int, "train": int, "eval": int}, "report.seeds", problems)
    for i, ds in enumerate(report.get("datasets") or []):
        where = f"report.datasets[{i}]"
        if _fields(ds, _DATASET_FIELDS, where, problems):
            fp = ds.get("fingerprint")
            if isinstance(fp, str) and not _FINGERPRINT_RE.match(fp):
                problems.append(f"{where}.fingerprint: expected 16-64 hex digits, got {fp!r}")
            if ds.get("source") not in DATA_SOURCES:
                problems.append(
                    f"{where}.source: expected one of {DATA_SOURCES}, got {ds.get('source')!r}"
                )
    for i, m in enumerate(report.get("models") or []):
        _fields(m, _MODEL_FIELDS, f"report.models[{i}]", problems)
    wall = report.get("wall_time_s")
    if isinstance(wall, dict):
        for k in _WALL_FIELDS:
            v = wall.get(k)
            if not _is_type(v, float) or (isinstance(v, float) and math.isfinite(v) and v < 0):
                problems.append(f"report.wall_time_s.{k}: expected a number >= 0, got {v!r}")
    rows = report.get("rows")
    if isinstance(rows, list):
        if not rows:
            problems.append("report.rows: empty")
        ids = set()
        for i, row in enumerate(rows):
            _check_row(row, f"report.rows[{i}]", problems)
            rid = row.get("id") if isinstance(row, dict) else None
            if rid in ids:
                problems.append(f"report.rows[{i}].id: duplicate {rid!r}")
            ids.add(rid)
    for i, v in enumerate(report.get("verdicts") or []):
        _fields(
            v,
            {"dataset": str, "model": str, "decomposes": (bool, type(None)), "message": str},
            f"report.verdicts[{i}]",
            problems,
        )
    for key in ("notes", "figures"):
        for i, s in enumerate(report.get(key) or []):
            if not isinstance(s, str):
                problems.append(f"report.{key}[{i}]: expected str, got {type(s).__name__}")
    _non_finite(report, "report", problems)
    return problems


def validate_report(report: Any) -> None:
    """Raise :class:`SchemaError` listing every violation, or return None if valid.

    Args:
        report: A report dict.

    Raises:
        SchemaError: If anything breaks the schema (see the module docstring).
    """
    problems = check_report(report)
    if problems:
        raise SchemaError(problems)
