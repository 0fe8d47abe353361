"""The paper's orderings, checked on measured rows: does the benchmark show what the paper says?

Where this sits: the table protocols (``benchmark.protocols.tables``) declare the
comparisons that the paper's text draws from each table as :class:`Ordering` objects;
:func:`check_orderings` reads the finished report rows and returns the report's
``orderings`` section. Nothing here trains or evaluates.

Two kinds of claim:

- ``above``: model A scores higher than model B on a metric (e.g. the full model far
  above "w/o NVS" on NV-ARI). It holds on the measured rows when A's value exceeds B's.
- ``close``: A is within ``tolerance`` points of B (e.g. the model trained on held-out
  appearances close to the CLEVR-567 model on the held-out test set). It holds when
  ``|A - B| <= tolerance``.

B may be a chance baseline (``b_source="baseline"``: the best baseline row on the same
table and dataset), for tables whose paper comparisons are between methods that the
benchmark does not train.

Values and margins are in the report's stored units (ARI family in percent, so a
``tolerance`` of 5 is 5 points on the paper's 0-100 scale).

Each entry gives the measured and paper values, whether the paper's own numbers keep the
claim, whether the measured rows do, the margin, and the seed-to-seed spread where rows of
more than one seed exist (``seed_spread``; null with a reason when one seed was run), so
that a margin smaller than the spread reads as "not shown". With other seeds the entry also
carries each seed's margin (``seed_margins``), their mean (``seed_mean``) and whether the
claim holds on that mean (``seed_mean_holds``): the figure a two-seed table quotes.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

__all__ = ["Ordering", "check_orderings", "orderings_summary", "other_seed_rows"]


@dataclass(frozen=True)
class Ordering:
    """One comparison the paper draws from a table.

    Attributes:
        table: paper table id (``tab:ablation``).
        claim: the sentence, as a reader would say it.
        metric: metric name of the rows (``fg_ari``).
        a_model / a_dataset: the row expected to be higher (or close).
        b_model / b_dataset: the row it is compared with; with ``b_source="baseline"``
            ``b_model`` is ignored and the best chance baseline of (table, b_dataset) is used.
        kind: ``above`` or ``close``.
        tolerance: points for ``close``.
    """

    table: str
    claim: str
    metric: str
    a_model: str
    a_dataset: str
    b_model: str
    b_dataset: str
    kind: str = "above"
    tolerance: float = 5.0
    b_source: str = "measured"

    def __post_init__(self) -> None:
        if self.kind not in ("above", "close"):
            raise ValueError(f"Ordering.kind must be 'above' or 'close', got {self.kind!r}")
        if self.b_source not in ("measured", "baseline"):
            raise ValueError(f"Ordering.b_source must be measured|baseline, got {self.b_source!r}")


def _value(rows: list[dict[str, Any]], table: str, model: str, dataset: str, source: str, m: str):
    for r in rows:
        if (r["source"], r["table"], r["model"], r["dataset"]) == (source, table, model, dataset):
            v = r["metrics"].get(m)
            return None if v is None else float(v)
    return None


def _best_baseline(rows: list[dict[str, Any]], table: str, dataset: str, m: str):
    best = None
    for r in rows:
        if r["source"] == "baseline" and r["table"] == table and r["dataset"] == dataset:
            v = r["metrics"].get(m)
            if v is not None and (best is None or v > best[1]):
                best = (r["model"], float(v))
    return best


def _holds(kind: str, a: float | None, b: float | None, tol: float) -> bool | None:
    if a is None or b is None:
        return None
    return a > b if kind == "above" else abs(a - b) <= tol


def _seed_stats(
    kind: str, tol: float, seed: int | None, margin: float | None, others: dict[int, float]
) -> dict[str, Any]:
    """Spread, per-seed margins, their mean and whether the claim holds on the mean."""
    if margin is None or not others:
        return {
            "seed_spread": None,
            "seed_spread_reason": "one seed measured: no seed-to-seed spread",
            "seed_margins": None,
            "seed_mean": None,
            "seed_mean_holds": None,
        }
    own = "this run" if seed is None else str(seed)
    by_seed = {own: margin, **{str(s): m for s, m in sorted(others.items())}}
    vals = list(by_seed.values())
    mean = sum(vals) / len(vals)
    return {
        "seed_spread": max(vals) - min(vals),
        "seed_spread_reason": None,
        "seed_margins": by_seed,
        "seed_mean": mean,
        "seed_mean_holds": _holds(kind, mean, 0.0, tol),
    }


def check_orderings(
    rows: list[dict[str, Any]],
    orderings: list[Ordering],
    seed_rows: dict[int, list[dict[str, Any]]] | None = None,
    seed: int | None = None,
) -> list[dict[str, Any]]:
    """The ``orderings`` section of a report.

    Args:
        rows: the report's rows (paper, measured, baseline).
        orderings: the comparisons of the report's tables; one whose row A is not in
            ``rows`` at all (a table or dataset the report leaves out) is skipped.
        seed_rows: optional rows of other seeds' reports of the same protocol, by seed; the
            spread of ``A - B`` over the seeds, each seed's margin and their mean are then
            reported.
        seed: this report's training seed (the key of its own margin in ``seed_margins``).

    Returns:
        One dict per ordering: table, claim, metric, kind, a / b (model, dataset, measured,
        paper), paper_holds, measured_holds (null when a value is missing), margin (A - B,
        measured), seed_spread and its reason when null, seed_margins (by seed),
        seed_mean and seed_mean_holds (null with one seed).
    """
    present = {(r["table"], r["model"], r["dataset"]) for r in rows}
    out = []
    for o in orderings:
        if (o.table, o.a_model, o.a_dataset) not in present:
            continue  # a table or dataset this report leaves out (e.g. --datasets)
        a_meas = _value(rows, o.table, o.a_model, o.a_dataset, "measured", o.metric)
        a_paper = _value(rows, o.table, o.a_model, o.a_dataset, "paper", o.metric)
        if o.b_source == "baseline":
            best = _best_baseline(rows, o.table, o.b_dataset, o.metric)
            b_name = f"best chance baseline ({best[0]})" if best else "best chance baseline"
            b_meas, b_paper = (best[1] if best else None), None
        else:
            b_name = o.b_model
            b_meas = _value(rows, o.table, o.b_model, o.b_dataset, "measured", o.metric)
            b_paper = _value(rows, o.table, o.b_model, o.b_dataset, "paper", o.metric)
        margins: dict[int, float] = {}
        for s, srows in (seed_rows or {}).items():
            a_s = _value(srows, o.table, o.a_model, o.a_dataset, "measured", o.metric)
            b_s = (
                (_best_baseline(srows, o.table, o.b_dataset, o.metric) or (None, None))[1]
                if o.b_source == "baseline"
                else _value(srows, o.table, o.b_model, o.b_dataset, "measured", o.metric)
            )
            if a_s is not None and b_s is not None:
                margins[s] = a_s - b_s
        margin = None if a_meas is None or b_meas is None else a_meas - b_meas
        measured_holds = _holds(o.kind, a_meas, b_meas, o.tolerance)
        out.append(
            {
                "table": o.table,
                "claim": o.claim,
                "metric": o.metric,
                "kind": o.kind,
                "tolerance": o.tolerance if o.kind == "close" else None,
                "a": {
                    "model": o.a_model,
                    "dataset": o.a_dataset,
                    "measured": a_meas,
                    "paper": a_paper,
                },
                "b": {
                    "model": b_name,
                    "dataset": o.b_dataset,
                    "measured": b_meas,
                    "paper": b_paper,
                },
                "paper_holds": _holds(o.kind, a_paper, b_paper, o.tolerance),
                "measured_holds": measured_holds,
                "margin": margin,
                **_seed_stats(o.kind, o.tolerance, seed, margin, margins),
                "why_null": None
                if measured_holds is not None
                else "a measured value is missing (row failed, not trained, left out or not computed)",
            }
        )
    return out


def orderings_summary(section: list[dict[str, Any]]) -> str:
    """One line: how many of the paper's comparisons the measured rows keep (and how many
    of those by less than their seed-to-seed spread, where other seeds were given)."""
    judged = [o for o in section if o["measured_holds"] is not None]
    held = sum(bool(o["measured_holds"]) for o in judged)
    missing = len(section) - len(judged)
    on_mean = [o for o in judged if o.get("seed_mean_holds") is not None]
    n_seeds = max((len(o["seed_margins"]) for o in on_mean), default=0)
    thin = sum(
        bool(o["measured_holds"])
        and o.get("seed_spread") is not None
        and abs(o["margin"]) < o["seed_spread"]
        for o in judged
    )
    return (
        f"The measured rows keep {held} of {len(judged)} of the paper's comparisons"
        + (f" ({missing} could not be judged: a value is missing)" if missing else "")
        + (
            f"; {thin} of those kept by a margin smaller than its seed-to-seed spread"
            if thin
            else ""
        )
        + (
            f"; on the mean margin of {n_seeds} seeds "
            f"{sum(bool(o['seed_mean_holds']) for o in on_mean)} of {len(on_mean)} hold"
            if on_mean
            else ""
        )
        + "; see 'orderings'."
    )


#: The settings two reports must share for their rows to count as two seeds of one table.
SPREAD_SETTINGS = ("train_steps_override", "train_minutes", "refine_slots", "refine_lr")


def other_seed_rows(
    reports: list[tuple[str, dict[str, Any]]],
    *,
    protocol: str,
    scale: str,
    seed: int,
    settings: dict[str, Any],
) -> dict[int, list[dict[str, Any]]]:
    """The measured and baseline rows of other seeds' reports, by seed (``--spread-from``).

    Args:
        reports: ``(path, report)`` pairs (:func:`benchmark.row_import.read_reports`).
        protocol, scale, seed: this run's; each report must be of the same protocol and
            scale and of another training seed.
        settings: this run's values of :data:`SPREAD_SETTINGS` (steps or minutes per model,
            test-time refinement); each report must have the same.

    Raises:
        ValueError: a report of another protocol, scale or budget, of this run's seed, or
            two reports of one seed (one line naming the report and the fix).
    """
    out: dict[int, list[dict[str, Any]]] = {}
    for path, rep in reports:
        where = f"--spread-from {path}"
        if rep.get("protocol") != protocol or rep.get("scale") != scale:
            raise ValueError(
                f"{where}: a {rep.get('protocol')!r} report at scale {rep.get('scale')!r}; "
                f"give a {protocol!r} report at scale {scale!r}"
            )
        other = (rep.get("seeds") or {}).get("train")
        if other is None:
            raise ValueError(f"{where}: the report names no training seed; give a newer report")
        if other == seed:
            raise ValueError(
                f"{where}: trained with seed {other}, the seed of this run; give a report "
                "of another --seed"
            )
        if other in out:
            raise ValueError(f"{where}: a second report of seed {other}; give one per seed")
        theirs = rep.get("scale_settings") or {}
        for key in SPREAD_SETTINGS:
            mine, their = settings.get(key), theirs.get(key)
            if key == "refine_slots":
                mine, their = mine or 0, their or 0
            if key == "refine_lr":  # a report without it refined at the rate of its day
                from benchmark.adapter import refinement_of

                their = refinement_of(theirs)[1]
            if mine != their:
                raise ValueError(
                    f"{where}: {key} {their!r} where this run has {mine!r}; its rows would "
                    "compare budgets, not seeds (give a report with the same --steps, "
                    "--train-minutes, --refine-slots and --refine-lr)"
                )
        out[other] = [r for r in rep.get("rows", []) if r.get("source") != "paper"]
    return out
