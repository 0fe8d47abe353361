"""Measured rows taken from earlier reports: ``benchmark run NAME --rows-from REPORT``.

A table at the ``cpu`` scale takes hours per model, more than one sitting, and the
machine that trained a model may be gone by the next one (its ``--out`` folder with it).
What survives is small: the committed ``report.json`` files. ``--rows-from`` lets a table
run take a measured row from such a report instead of training and scoring its model
again, when the number would be the one this run computes:

- the report was written under the same *row context* as this run (``row_context``: the
  scale's settings, seeds, adapter and evaluation versions, step override and LPIPS
  availability, the context of :class:`benchmark.report.RowStore`);
- the row's model key (``run_key``: data fingerprint, model and training configs, seed,
  training budget) and test-data fingerprint equal this run's;
- it holds every metric this run's row shows (a row of another table scored on the same
  model and test data serves as well: one evaluation computes all metrics).

A wall-clock-budgeted model is not reproducible step for step, so a taken row keeps its
provenance (``imported_from``: the report, when it was written, at which commit) and its
model's entry (steps, wall time) goes into this report's ``models``. Reports written
before ``row_context`` existed are refused, with the reason in the notes.

The report's notes on training speed live here too: :func:`step_rate_note` (models of one
table trained at different rates) and :func:`recipe_rate_note` (a machine slower than the
ones the cpu recipe was measured on).

Where this sits: :class:`benchmark.context.Context` reads the files (a bad path is a
one-line error before any work), :func:`benchmark.runner.run_table_protocol` asks
:meth:`ImportedRows.row` before training a row's model.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from benchmark.datasets import DatasetInfo
from benchmark.evaluate import EvalResult
from benchmark.report import stable_hash
from benchmark.rows import MeasuredRow, measured_row, row_metrics
from benchmark.schema import REPORT_KIND
from svorf.registry import SCALES as SVORF_SCALES

_CPU_RECIPE = SVORF_SCALES["cpu"].recipe
assert _CPU_RECIPE is not None and _CPU_RECIPE.steps_per_minute is not None
_CPU_RECIPE_RATES = _CPU_RECIPE.steps_per_minute

__all__ = [
    "RECIPE_STEPS_PER_MINUTE",
    "ImportedRows",
    "read_reports",
    "recipe_rate_note",
    "step_rate_note",
]


def read_reports(
    paths: list[str] | tuple[str, ...], flag: str = "--rows-from"
) -> list[tuple[str, dict[str, Any]]]:
    """``(path, report)`` of each file given to ``flag`` (a folder means its report.json).

    Raises:
        ValueError: a file that is missing, not JSON or not a benchmark report (one line).
    """
    out = []
    for raw in paths:
        p = Path(raw)
        if p.is_dir():
            p = p / "report.json"
        try:
            report = json.loads(p.read_text())
        except FileNotFoundError:
            raise ValueError(
                f"{flag} {raw}: no such file (give a report.json or its folder, e.g. "
                "results/cpu/segmentation-60min)"
            ) from None
        except (OSError, ValueError) as err:
            raise ValueError(f"{flag} {raw}: not a readable JSON report ({err})") from None
        if not isinstance(report, dict) or report.get("kind") != REPORT_KIND:
            raise ValueError(
                f"{flag} {raw}: not a benchmark report (its 'kind' is not {REPORT_KIND!r})"
            )
        out.append((str(p), report))
    return out


@dataclass
class _Evaluation:
    """The scores of one (model key, test data) pair in one earlier report."""

    source: dict[str, Any]
    n_scenes: int
    train_dataset: str
    metrics: dict[str, Any] = field(default_factory=dict)
    null_reasons: dict[str, str] = field(default_factory=dict)
    nan_counts: dict[str, int] = field(default_factory=dict)
    eval_wall_s: float = 0.0
    details: dict[str, Any] = field(default_factory=dict)


def _context_difference(theirs: str, context: dict[str, Any] | None, report: dict[str, Any]) -> str:
    """What differs between a report's row context ``theirs`` and this run's ``context``,
    where one change to the latter gives the former: LPIPS availability or the seeds."""
    if context is not None:
        if stable_hash({**context, "lpips": not context.get("lpips")}) == theirs:
            if context.get("lpips"):
                return "that report was scored without LPIPS weights, this run has them"
            return (
                "that report was scored with LPIPS weights, which this machine lacks (run "
                "`benchmark lpips-weights`, or pass --lpips-weights FILE)"
            )
        seeds = report.get("seeds")
        if seeds != context.get("seeds") and stable_hash({**context, "seeds": seeds}) == theirs:
            return f"that report is of seeds {seeds}, this run of {context.get('seeds')}"
    return (
        "other scale settings, seeds, evaluation version, dataset fingerprint scheme, "
        "--steps or LPIPS availability"
    )


class ImportedRows:
    """The measured scores of earlier reports that a run with ``context_hash`` may take.

    Args:
        reports: ``(path, report)`` pairs from :func:`read_reports`, in priority order
            (the first report holding a (model key, test data) pair supplies it).
        context_hash: this run's row context (``RowStore.context_hash``).
        context: what that hash is of (the ``RowStore`` context); when given, a refusal
            names the difference where it is one of LPIPS availability or the seeds.
    """

    def __init__(
        self,
        reports: list[tuple[str, dict[str, Any]]],
        context_hash: str,
        context: dict[str, Any] | None = None,
    ) -> None:
        self.evals: dict[tuple[str, str], _Evaluation] = {}
        self.models: dict[str, dict[str, Any]] = {}
        #: Why reports (or parts of them) were not used; for the report's notes.
        self.refused: list[str] = []
        for path, report in reports:
            theirs = report.get("row_context")
            if theirs != context_hash:
                why = (
                    "written before reports recorded their row context"
                    if theirs is None
                    else f"row context {theirs}, this run's {context_hash}: "
                    + _context_difference(theirs, context, report)
                )
                self.refused.append(f"{path}: none of its rows taken ({why})")
                continue
            source = {
                "report": path,
                "created_utc": report.get("created_utc"),
                "commit": (report.get("git") or {}).get("commit"),
            }
            mine: set[tuple[str, str]] = set()
            for row in report.get("rows", []):
                if row.get("source") != "measured" or row.get("n_scenes", 0) <= 0:
                    continue
                pair = (row.get("run_key"), row.get("test_fingerprint"))
                if not all(isinstance(x, str) for x in pair):
                    continue
                if pair in self.evals and pair not in mine:
                    continue  # an earlier report supplies this pair
                ev = self.evals.setdefault(
                    pair,
                    _Evaluation(source, int(row["n_scenes"]), str(row.get("train_dataset", ""))),
                )
                mine.add(pair)
                for m, v in row.get("metrics", {}).items():
                    if v is not None or m not in ev.metrics:
                        ev.metrics[m] = v
                        if v is None:
                            ev.null_reasons[m] = row.get("null_reasons", {}).get(m, "not_computed")
                        else:
                            ev.null_reasons.pop(m, None)
                ev.nan_counts.update(row.get("nan_counts", {}))
                ev.details.update(row.get("details", {}))
                ev.eval_wall_s = max(ev.eval_wall_s, float(row.get("eval_wall_s", 0.0)))
            for m in report.get("models", []):
                key = m.get("run_key")
                if any(k == key for k, _ in mine) and key not in self.models:
                    self.models[key] = {**m, "reused": True, "imported_from": source}

    def row(self, spec: MeasuredRow, run_key: str, test: DatasetInfo) -> dict[str, Any] | None:
        """The row of ``spec`` from the imported scores of model ``run_key`` on ``test``
        (with ``imported_from``), or None when no report holds that pair with every metric
        the row shows."""
        ev = self.evals.get((run_key, test.fingerprint))
        names = row_metrics(spec)
        if ev is None or any(m not in ev.metrics for m in names):
            return None
        res = EvalResult(
            metrics=dict(ev.metrics),
            null_reasons=dict(ev.null_reasons),
            n_scenes=ev.n_scenes,
            nan_counts=dict(ev.nan_counts),
            wall_s=ev.eval_wall_s,
            details=dict(ev.details),
        )
        row = measured_row(spec, run_key, ev.train_dataset, test, res).to_dict()
        row["imported_from"] = dict(ev.source)
        return row


def step_rate_note(models: list[dict[str, Any]], spread: float = 1.25) -> str | None:
    """A note for a table whose models trained at step rates ``spread`` or more apart.

    Under one wall-clock budget a model's steps depend on the machine and its load; a
    table built over several sittings (rows taken with ``--rows-from``) can mix a model
    from a machine at half the speed of another's. ``models`` are report ``models``
    entries (``steps_done``, ``train_wall_s``, ``variant``, ``train_dataset``, and
    ``imported_from`` where taken). None when fewer than two rates are known or they are
    within ``spread`` of each other.
    """
    rates = []
    for m in models:
        steps, wall = m.get("steps_done"), m.get("train_wall_s")
        if isinstance(steps, int) and isinstance(wall, (int, float)) and wall > 0 and steps > 0:
            rates.append((steps / (wall / 60.0), m))
    if len(rates) < 2:
        return None
    (lo, m_lo), (hi, m_hi) = min(rates, key=lambda r: r[0]), max(rates, key=lambda r: r[0])
    if hi < spread * lo:
        return None

    def name(m: dict[str, Any]) -> str:
        where = m.get("imported_from")
        tail = (
            f", from {where['report']}" if isinstance(where, dict) else ", trained into this --out"
        )
        return f"{m.get('variant')} on {m.get('train_dataset')}{tail}"

    return (
        f"The models' training speeds differ by {hi / lo:.1f}x: from {lo:.0f} steps per "
        f"minute ({name(m_lo)}) to {hi:.0f} ({name(m_hi)}). Variants differ in the cost of "
        "a step, and machines and their load differ between sittings, so under one budget "
        "some models made more steps than others; compare rows by steps as well (models)."
    )


#: Training speeds (steps per minute, alone on 2 cores) at which the cpu recipe's CLEVR-567
#: results were measured: 25,606-25,744 steps in 60 minutes and 51,282-52,765 in 120 (seeds
#: 0 and 1, 2026-11-30; docs/notes/cpu_recipe.md). The 120-minute models, at about twice the
#: steps, scored FG-ARI 1.0-5.2 points above the 60-minute ones. The recipe's own record
#: (``svorf.registry.Recipe.steps_per_minute``), which ``svorf train`` checks early.
RECIPE_STEPS_PER_MINUTE: tuple[float, float] = _CPU_RECIPE_RATES


def recipe_rate_note(models: list[dict[str, Any]], below: float = 0.8) -> str | None:
    """A note for full recipe models that trained at under ``below`` x the rates of
    :data:`RECIPE_STEPS_PER_MINUTE`: a wall-clock budget measures the machine as well as
    the recipe, so a "does NOT decompose" on a slow machine is read with its steps.
    ``models`` are report ``models`` entries (the ablation variants cost other amounts
    per step and are left out); None when no such model is that slow."""
    lo, hi = RECIPE_STEPS_PER_MINUTE
    slow = []
    for m in models:
        steps, wall = m.get("steps_done"), m.get("train_wall_s")
        recipe = "recipe" in str(m.get("config_source", ""))
        budgeted = (m.get("train_budget") or {}).get("minutes") is not None
        if not recipe or m.get("variant") != "full" or not budgeted:
            continue
        if not (isinstance(steps, int) and isinstance(wall, (int, float)) and wall > 0):
            continue
        rate = steps / (wall / 60.0)
        if rate < below * lo:
            slow.append(
                f"{m.get('train_dataset')} at {rate:.0f} steps per minute ({steps} steps in "
                f"{wall / 60.0:.0f} min; 60 minutes there are about {60.0 * lo / rate:.0f} "
                "here)"
            )
    if not slow:
        return None
    return (
        "The cpu recipe's model trained slower than on the machines its results were "
        "measured on: "
        + "; ".join(slow)
        + f". Those made {lo:.0f}-{hi:.0f} steps per minute alone on 2 cores (about 25,700 "
        "steps in 60 minutes, where the CLEVR-567 verdict held at seeds 0 and 1; "
        "docs/notes/cpu_recipe.md), and at 120 minutes, about twice the steps, FG-ARI was "
        "1.0-5.2 points higher: fewer steps cost points. Compare models by steps "
        "(models), not only by minutes."
    )
