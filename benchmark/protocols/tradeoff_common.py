"""Settings and pieces shared by the ``tradeoff`` protocol's curves.

Where this sits: :mod:`benchmark.protocols.tradeoff` runs the protocol; each curve has its
module (:mod:`.tradeoff_step`, :mod:`.tradeoff_render`, :mod:`.tradeoff_training`,
:mod:`.tradeoff_generator`) and the fronts theirs (:mod:`.tradeoff_pareto`). This module
holds what several of them need: how hard each scale measures (:data:`SETTINGS`), the
weight sets the step and render curves use (:class:`WeightSet`), label formatting and the
progress line.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch

from benchmark.log import log

__all__ = [
    "SETTINGS",
    "TradeoffSettings",
    "WeightSet",
    "fmt_value",
    "knobs_text",
    "log_tradeoff",
]


@dataclass(frozen=True)
class TradeoffSettings:
    """How hard one scale measures.

    Attributes:
        repeats: timed interleaved repeats (the median is taken over them).
        warmup: untimed repeats before (allocator, caches).
        threads: torch intra-op threads during the run (None = leave as is).
        sharp: add the ``sharp-m`` weight set.
        render_scenes: test scenes each point of the render curve renders (every view).
        render_repeats: timed interleaved repeats of the render curve.
        generator_scenes: clevr567 test scenes of the generator curve (every view).
        generator_ref_samples: samples per pixel of its reference render.
        generator: measure the generator curve (needs bpy).
    """

    repeats: int
    warmup: int
    threads: int | None
    sharp: bool = True
    render_scenes: int = 2
    render_repeats: int = 1
    generator_scenes: int = 1
    generator_ref_samples: int = 64
    generator: bool = True


SETTINGS: dict[str, TradeoffSettings] = {
    # Tiny model, 2 scenes x 64 rays: seconds; one thread so tests stay quiet on 2 cores.
    "smoke": TradeoffSettings(repeats=3, warmup=1, threads=1),
    # The cpu-scale model and batch (4 x 128 rays) on a 2-core machine: minutes; the render
    # curve renders 4 test scenes x 4 views at 64x64 per point (~0.3-0.6 s per view).
    # The generator curve: 2 scenes x 4 views at 64x64 against a 512-sample reference.
    "cpu": TradeoffSettings(
        repeats=7,
        warmup=2,
        threads=2,
        render_scenes=4,
        render_repeats=2,
        generator_scenes=2,
        generator_ref_samples=512,
    ),
    # The paper's model and batch (16 x 64 rays); meant for a GPU.
    "paper": TradeoffSettings(
        repeats=5,
        warmup=2,
        threads=None,
        render_scenes=8,
        render_repeats=2,
        generator_scenes=4,
        generator_ref_samples=512,
    ),
}


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
