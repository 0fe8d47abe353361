"""Settings and pieces shared by the ``tradeoff`` protocol's curves.

Where this sits: :mod:`benchmark.protocols.tradeoff` runs the protocol; each curve has its
module (:mod:`.step`, :mod:`.render`, :mod:`.training`, :mod:`.generator`) and the fronts
theirs (:mod:`.pareto`). This module holds what several of them need: how hard each scale
measures (:data:`SETTINGS`, defined with the benchmark's other per-scale settings in
:mod:`benchmark.scales`), the weight sets the step and render curves use
(:class:`WeightSet`), label formatting and the progress line.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch

from benchmark.log import log
from benchmark.scales import TRADEOFF, TradeoffSettings

__all__ = [
    "SETTINGS",
    "TradeoffSettings",
    "WeightSet",
    "fmt_value",
    "knobs_text",
    "log_tradeoff",
]


#: How hard each scale measures (``benchmark.scales.TRADEOFF``, the benchmark's per-scale
#: settings).
SETTINGS: dict[str, TradeoffSettings] = TRADEOFF


@dataclass
class WeightSet:
    """Weights shared by a group of points, and their knob-free configuration."""

    name: str
    table: str
    base: Any  # svorf ModelConfig with every knob off
    state: dict[str, torch.Tensor]
    sharpen: float
    knobs: tuple[str, ...]
    description: str
    run_key: str | None = None
    shipped: Any = None
    """The model config as shipped / trained (speed knobs as configured): the render
    curve's default point. None = ``base``."""
    run_dir: Path | None = None


def fmt_value(v: Any) -> str:
    """A setting as the points' labels show it (``None``, ``0.99``, ``True``)."""
    return "None" if v is None else (f"{v:g}" if isinstance(v, float) else str(v))


def knobs_text(d: dict[str, Any]) -> str:
    """Knob settings in a label: ``bf16=True, keep=0.99`` (short knob names)."""
    short = {"bf16_autocast": "bf16", "slot_keep_mass": "keep", "slot_topk": "topk"}
    return ", ".join(f"{short.get(k, k)}={fmt_value(v)}" for k, v in d.items())


def log_tradeoff(msg: str) -> None:
    """A ``[benchmark] tradeoff: ...`` progress line (:func:`benchmark.log.log`)."""
    log(f"tradeoff: {msg}")
