"""The protocol engine of the paper's tables: datasets -> cached models -> cached
evaluations -> rows -> report.

Where this sits: a table protocol (:mod:`benchmark.protocols.tables`) declares its rows
with :class:`ModelJob` / :class:`MeasuredRow` and hands them, with the run's
:class:`Context`, to :func:`run_table_protocol`. The pieces live beside it: the run context
and its caches in :mod:`benchmark.context`, the units of work (training, evaluation) in
:mod:`benchmark.jobs` (as Ray tasks: :mod:`benchmark.ray_jobs`), the rows and verdicts in
:mod:`benchmark.rows`; their public names are re-exported here.

Resume: rows are kept in ``<out>/<protocol>-<scale>/rows/<row id>.json``; a rerun skips
finished rows whose test data, model key and evaluation version are still the ones this
run would use (models and evaluations are cached by :class:`Context`).

``--datasets`` (``Context.only_datasets``) keeps the measured and paper rows of the
named test datasets of a table protocol; the report's notes name the ones left out.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from pathlib import Path
from typing import Any

from benchmark import adapter
from benchmark.context import BACKENDS, BUDGET_STEP_CAP, Context, ModelRecord
from benchmark.evaluate import EVAL_VERSION
from benchmark.generator_bridge import DatasetUnavailable
from benchmark.jobs import ModelJob, evaluate_run, read_eval, train_run, write_eval
from benchmark.log import log
from benchmark.orderings import Ordering, check_orderings, orderings_summary
from benchmark.paper_numbers import PAPER_TABLES, paper_rows
from benchmark.report import RowStore
from benchmark.row_import import ImportedRows
from benchmark.rows import (
    MeasuredRow,
    chance_baseline_rows,
    measured_row,
    row_id,
    row_metrics,
    unavailable_row,
    verdicts_for,
)

__all__ = [
    "BACKENDS",
    "BUDGET_STEP_CAP",
    "Context",
    "MeasuredRow",
    "ModelJob",
    "ModelRecord",
    "evaluate_run",
    "planned_models",
    "read_eval",
    "row_id",
    "row_metrics",
    "run_table_protocol",
    "train_run",
    "verdicts_for",
    "write_eval",
]


def _filter_datasets(
    ctx: Context, measured: list[MeasuredRow]
) -> tuple[list[MeasuredRow], set[str] | None, list[str]]:
    """Apply ``ctx.only_datasets``: ``(kept rows, kept test datasets or None, left out)``.

    Raises:
        ValueError: a name that is not a test dataset of this protocol (one line,
            naming the valid ones).
    """
    kept, left_out = ctx.select_datasets([s.dataset for s in measured])
    if ctx.only_datasets is None:
        return measured, None, []
    keep = set(kept)
    return [s for s in measured if s.dataset in keep], keep, left_out


def _is_current(
    row: dict[str, Any] | None, spec: MeasuredRow, run_key: str, test_fingerprint: str
) -> bool:
    """Whether a stored or imported ``row`` is this run's row of ``spec``: the same model,
    test data and columns."""
    return (
        row is not None
        and row.get("test_fingerprint") == test_fingerprint
        and row.get("run_key") == run_key
        and set(row.get("metrics", {})) == set(row_metrics(spec))
    )


def planned_models(ctx: Context, measured: list[MeasuredRow]) -> list[ModelJob]:
    """The models a table protocol would train for ``measured`` under ``ctx`` (after
    ``--datasets``), each once, a model's initialising model first; reads no data.

    Raises:
        ValueError: as :func:`run_table_protocol` for an unknown ``--datasets`` name.
    """
    kept, _, _ = _filter_datasets(ctx, measured)
    jobs: list[ModelJob] = []

    def add(job: ModelJob) -> None:
        init = ctx.init_job(job)
        if init is not None:
            add(init)
        if job not in jobs:
            jobs.append(job)

    for spec in kept:
        add(spec.job)
    return jobs


def run_table_protocol(
    ctx: Context,
    tables: list[str],
    measured: list[MeasuredRow],
    figures: Callable[[Context, list[dict[str, Any]], dict[str, Any]], list[str]] | None = None,
    orderings: list[Ordering] | None = None,
) -> Path:
    """Run a protocol made of paper tables: train/evaluate every measured row, write the report.

    Args:
        ctx: the run context.
        tables: paper table ids whose paper rows go into the report.
        measured: the measured rows (one model evaluation each; models and
            evaluations are shared through the caches).
        figures: ``fn(ctx, rows, state) -> [file names]`` drawing into ``ctx.report_dir``.
        orderings: the paper's comparisons for these tables; checked on the rows into the
            report's ``orderings`` section (``benchmark.orderings``).

    Returns:
        Path of the written ``report.json``.
    """
    for t in tables:
        if t not in PAPER_TABLES:
            raise ValueError(f"unknown paper table {t!r}")
    measured, keep, left_out = _filter_datasets(ctx, measured)
    if ctx.backend == "ray":
        from benchmark.ray_jobs import run_jobs_on_ray

        # Datasets, training runs and evaluations as Ray tasks; the loop below then finds
        # every one of them in the caches and only assembles the rows.
        run_jobs_on_ray(ctx, measured)
    report = ctx.base_report()
    store_ctx = {
        "scale": ctx.scale,
        "settings": ctx.settings.to_dict(),
        "source": ctx.data_source,
        "seeds": ctx.seeds,
        "adapter": adapter.ADAPTER_VERSION,
        "eval": EVAL_VERSION,
        "train_steps": ctx.train_steps,
        "lpips": ctx.lpips_available(),
        # Dataset fingerprints (in every row's keys) round numbers since 2026-11-27, so
        # that splits generated on different CPUs match; earlier reports used raw bytes.
        "fingerprint": "rounded-1e-6",
    }
    # Only when on: rows scored from the encoder's slots keep their context.
    store_ctx.update(ctx.refine_context())
    store = RowStore(ctx.report_dir / "rows", store_ctx)
    # The row context goes into the report, so that a later run can take its rows
    # (--rows-from) only where they are the numbers it would compute.
    report["row_context"] = store.context_hash
    imported = None
    if ctx.rows_from:
        imported = ImportedRows(ctx.rows_from, store.context_hash, store_ctx)
        for why in imported.refused:  # now, before hours of training, and in the notes
            log(f"--rows-from {why}")
    taken: list[str] = []
    rows: list[dict[str, Any]] = []
    for t in tables:
        rows.extend(r for r in paper_rows(t) if keep is None or r["dataset"] in keep)
    if left_out:
        ctx.notes.append(
            f"Datasets left out by --datasets {','.join(ctx.only_datasets or ())}: "
            f"{', '.join(left_out)} (neither their measured nor their paper rows are in "
            "this report)."
        )
    state: dict[str, Any] = {"records": {}, "tests": {}}
    skipped = 0
    unavailable: list[str] = []
    failed: list[str] = []
    not_trained: list[str] = []
    for spec in measured:
        rid = row_id(spec.table, spec.model, spec.dataset, "measured")
        try:
            test = ctx.dataset(spec.dataset, "test")
            if (
                not ctx.may_train(spec.job)
                and imported is None
                and store.get(rid) is None
                and ctx.no_cached_run(spec.job)
            ):  # no run can be its model: do not generate its training split to hash it
                state["tests"][spec.dataset] = test
                not_trained.append(f"{spec.table} / {spec.model} / {spec.dataset}")
                rows.append(
                    unavailable_row(
                        spec, ctx.not_trained_why(spec.job), kind="not_trained"
                    ).to_dict()
                )
                continue
            ctx.train_dataset(spec.job)
        except DatasetUnavailable as err:
            log(f"row {spec.table} / {spec.model} / {spec.dataset}: dataset unavailable: {err}")
            unavailable.append(f"{spec.table} / {spec.model} / {spec.dataset}: {err}")
            rows.append(unavailable_row(spec, str(err)).to_dict())
            continue
        state["tests"][spec.dataset] = test
        key = ctx.model_key(spec.job)[0]
        stored = store.get(rid)
        if not _is_current(stored, spec, key, test.fingerprint) and imported is not None:
            stored = imported.row(spec, key, test)
            if stored is not None:
                store.put(stored)  # a rerun with this --out keeps it
        if stored is not None and _is_current(stored, spec, key, test.fingerprint):
            where = stored.get("imported_from")
            if where is not None:
                log(
                    f"row taken from {where['report']}: {spec.table} / {spec.model} / {spec.dataset}"
                )
                taken.append(f"{spec.table} / {spec.model} / {spec.dataset} from {where['report']}")
                entry = imported.models.get(stored["run_key"]) if imported is not None else None
                if entry is not None:
                    ctx.imported_models.setdefault(stored["run_key"], entry)
            else:
                log(f"row done, skipped: {spec.table} / {spec.model} / {spec.dataset}")
                skipped += 1
            rows.append(stored)
            # Keep the model in the report if its run is still on disk (never retrain here).
            rec = ctx.model(spec.job, train=False)
            if rec is not None:
                state["records"][(spec.job, spec.dataset)] = rec
            continue
        try:
            rec = ctx.model(spec.job, train=ctx.may_train(spec.job))
            if rec is None:  # --no-train / --train-only and no finished cached run
                why = ctx.not_trained_why(spec.job)
                not_trained.append(f"{spec.table} / {spec.model} / {spec.dataset}")
                rows.append(unavailable_row(spec, why, kind="not_trained").to_dict())
                continue
            res = ctx.evaluation(rec, test)
        except Exception as err:  # noqa: BLE001 - one failing row must not lose the others
            why = f"{type(err).__name__}: {err}".splitlines()[0]
            log(f"row {spec.table} / {spec.model} / {spec.dataset}: FAILED: {why}")
            failed.append(f"{spec.table} / {spec.model} / {spec.dataset}: {why}")
            rows.append(unavailable_row(spec, why, kind="failed").to_dict())
            continue
        row = measured_row(spec, rec.key, rec.train_dataset.name, test, res).to_dict()
        store.put(row)
        rows.append(row)
        state["records"][(spec.job, spec.dataset)] = rec
    # Chance baselines per (table, test dataset), with the slot count of that table's models.
    seen = set()
    for spec in measured:
        k = (spec.table, spec.dataset)
        if k in seen:
            continue
        seen.add(k)
        test = state["tests"].get(spec.dataset)
        if test is None:
            continue
        k_slots = int(ctx.configs(spec.job)[0].num_slots)
        metrics = tuple(
            dict.fromkeys(m for s in measured if (s.table, s.dataset) == k for m in s.metrics)
        )
        chance = chance_baseline_rows(
            spec.table, spec.dataset, metrics, ctx.baselines(test, k_slots)
        )
        rows.extend(r.to_dict() for r in chance)
    if failed:
        report["status"] = "partial"
        ctx.notes.insert(
            0,
            f"{len(failed)} measured row(s) FAILED (metrics null, reason 'failed: ...'; the "
            "command exits non-zero): " + "; ".join(failed),
        )
    if not_trained:
        report["status"] = "partial"
        ctx.notes.append(
            "Rows not trained in this run (--no-train or --train-only; metrics null, reason "
            "'not_trained'): " + "; ".join(not_trained)
        )
    if unavailable:
        report["status"] = "partial"
        ctx.notes.append(
            "Rows without data (metrics null, reason 'dataset_unavailable'): "
            + "; ".join(unavailable)
        )
    if taken:
        ctx.notes.append(
            f"{len(taken)} measured row(s) were taken from earlier reports (--rows-from; "
            "same row context, model key and test data; each row's imported_from says "
            "which report and commit, its model's entry in models how many steps): "
            + "; ".join(taken)
        )
    if imported is not None and imported.refused:
        ctx.notes.append("--rows-from: " + "; ".join(imported.refused))
    if skipped:
        ctx.notes.append(
            f"{skipped} measured row(s) were finished by an earlier invocation and reused."
        )
    # Order: by table, then paper / measured / baseline, keeping declaration order within.
    order = {t: i for i, t in enumerate(tables)}
    src = {"paper": 0, "measured": 1, "baseline": 2}
    rows.sort(key=lambda r: (order.get(r["table"], 99), src[r["source"]]))
    report["rows"] = rows
    report["verdicts"] = verdicts_for(rows, ctx.settings)
    if orderings:
        report["orderings"] = check_orderings(
            rows, orderings, seed_rows=ctx.seed_rows, seed=ctx.seeds["train"]
        )
        ctx.notes.append(orderings_summary(report["orderings"]))
        if ctx.seed_rows:
            ctx.notes.append(
                f"Seed-to-seed spread (--spread-from): each ordering's seed_spread is the "
                f"range of its margin over seed {ctx.seeds['train']} (this run) and seed(s) "
                + ", ".join(str(s) for s in sorted(ctx.seed_rows))
                + " ("
                + ", ".join(ctx.spread_from)
                + "); seed_margins gives each seed's margin and seed_mean their mean; the "
                "measured rows and verdicts are this run's seed alone. A margin smaller than "
                "its spread is not shown by these seeds."
            )
    for r in rows:
        psnr = r["metrics"].get("psnr") if r["source"] == "measured" else None
        flat = next(
            (
                b["metrics"].get("psnr")
                for b in rows
                if b["source"] == "baseline"
                and b["table"] == r["table"]
                and b["dataset"] == r["dataset"]
                and b["metrics"].get("psnr") is not None
            ),
            None,
        )
        if psnr is not None and flat is not None:
            word = "above" if psnr > flat + 1.0 else "NOT clearly above (within 1 dB or below)"
            ctx.notes.append(
                f"{r['table']} / {r['model']} / {r['dataset']}: novel-view PSNR {psnr:.1f} dB is "
                f"{word} the flat median-colour baseline {flat:.1f} dB."
            )
    judged = [v for v in report["verdicts"] if v["decomposes"] is not None]
    if judged:
        n_ok = sum(v["decomposes"] for v in judged)
        head = (
            f"At scale '{ctx.scale}' NO measured model decomposes the scenes"
            if n_ok == 0
            else f"At scale '{ctx.scale}' {n_ok} of {len(judged)} measured rows decompose the scenes"
        )
        ctx.notes.insert(
            0,
            f"{head} (criterion: FG-ARI >= {ctx.settings.decompose_threshold:.0f}, >= the best "
            f"chance baseline on the same test set + {ctx.settings.decompose_margin:.0f}, and >= "
            f"the model's own FG-ARI with another scene's slots (fg_ari_shuffled) + "
            f"{ctx.settings.decompose_margin:.0f}; see verdicts).",
        )
    lp = [r for r in rows if r["null_reasons"].get("lpips") == "lpips_unavailable"]
    if lp:
        why = next(
            (r.get("details", {}).get("lpips") for r in lp if r.get("details", {}).get("lpips")),
            None,
        )
        ctx.notes.append("LPIPS is null: " + (why or "AlexNet LPIPS weights not found locally."))
    if figures is not None:
        report["figures"] = figures(ctx, rows, state)
    if ctx.refine_slots:
        ctx.notes.append(
            f"Test-time slot refinement (--refine-slots {ctx.refine_slots} --refine-lr "
            f"{ctx.refine_lr:g}): before every prediction the encoder's slots were refined by "
            f"{ctx.refine_slots} Adam steps at learning rate {ctx.refine_lr:g} "
            "(every network frozen) to reproduce the input view's own pixels; no other view, "
            "mask or depth is read. The paper's evaluation uses the encoder's slots alone "
            "(--refine-slots 0), so these rows are not comparable with its numbers."
        )
    ctx.notes.extend(ctx.settings.notes)
    return ctx.finish(report)


def finite(x: Any) -> bool:
    """Whether ``x`` is a finite int or float."""
    return isinstance(x, (int, float)) and math.isfinite(x)
