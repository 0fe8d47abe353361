"""Benchmark protocols, one function each: ``fn(ctx) -> report path``.

- ``segmentation``, ``nvs``, ``ablation``, ``generalization``: the paper's tables
  (:mod:`.tables`).
- ``speed``: training steps/s, peak memory and render time per view (:mod:`.speed`).
- ``stability``: volume-rendering stress against a float64 reference (:mod:`.stability`).
- ``tradeoff``: a time-vs-error curve for every speed knob of the model (:mod:`.tradeoff`).
- ``editing``: moved-object and changed-background renders against re-rendered ground
  truth of the manipulation split (:mod:`.editing`).
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

from benchmark.context import Context
from scenefmt.cli_util import choose

__all__ = [
    "MODEL_PROTOCOLS",
    "PROTOCOLS",
    "TABLE_PROTOCOLS",
    "NotImplementedProtocol",
    "get_protocol",
]


class NotImplementedProtocol(NotImplementedError):
    """A listed protocol that has no implementation yet (none today; kept so that
    callers catching it keep working)."""


def _lazy(module: str, name: str) -> Callable[[Context], Path]:
    def run(ctx: Context) -> Path:
        import importlib

        return getattr(importlib.import_module(f"benchmark.protocols.{module}"), name)(ctx)

    run.__name__ = name
    return run


#: Protocol name -> function: every protocol of ``benchmark.schema.PROTOCOLS``.
PROTOCOLS: dict[str, Callable[[Context], Path]] = {
    "segmentation": _lazy("tables", "run_segmentation"),
    "nvs": _lazy("tables", "run_nvs"),
    "ablation": _lazy("tables", "run_ablation"),
    "generalization": _lazy("tables", "run_generalization"),
    "speed": _lazy("speed", "run_speed"),
    "tradeoff": _lazy("tradeoff", "run_tradeoff"),
    "stability": _lazy("stability", "run_stability"),
    "editing": _lazy("editing", "run_editing"),
}


#: Protocols made of paper tables (``run_table_protocol``); ``--backend ray``,
#: ``--address`` and ``--show-config`` apply to them only.
TABLE_PROTOCOLS: tuple[str, ...] = ("segmentation", "nvs", "ablation", "generalization")

#: Protocols that train models (through ``Context.model``, one cache shared by all of
#: them) and have a dataset axis: ``--datasets``, ``--train-minutes`` and ``--no-train``
#: apply to them, and a model one of them trained is reused by the others.
MODEL_PROTOCOLS: tuple[str, ...] = (*TABLE_PROTOCOLS, "editing")


def get_protocol(name: str) -> Callable[[Context], Path]:
    """The protocol function; a one-line ValueError naming the known protocols otherwise
    ("did you mean ...?" for a near miss)."""
    return PROTOCOLS[choose(name, PROTOCOLS, "protocol")]
