"""Merge benchmark reports into ``leaderboard.json`` and print it beside the paper.

Where this sits: ``benchmark leaderboard DIR`` walks ``DIR`` for ``report.json``
files (every protocol writes one), validates each against the schema, keeps the
newest row per (protocol, scale, table, model, dataset, source, training seed of a
measured row, data seed of a baseline's test scenes), preferring a measured row whose
model has the configs the recipe gives today (``current_recipe``) over a lever's or an
older recipe's, and a model of a minute budget trained at the recipe's speed over one
trained on a slower machine (``slow_machine``), and writes ``DIR/leaderboard.json``. The
printed table puts every measured and baseline row under the paper's rows of the same
table, formatted by :mod:`benchmark.display` and at most :data:`WIDTH` columns wide. ``leaderboard.json``
keeps the reports' stored values (ARI family in percent, like ``report.json``).
"""

from __future__ import annotations

import json
import os
import textwrap
from pathlib import Path
from typing import Any

from benchmark import adapter
from benchmark.display import (
    LEGEND,
    NULL,
    fmt_metric,
    metric_label,
    reason_text,
    table_description,
    table_title,
)
from benchmark.html import metric_columns
from benchmark.paper_numbers import PAPER_TABLES
from benchmark.report import utc_now, write_json
from benchmark.row_import import recipe_rate_note
from benchmark.schema import SchemaError, validate_report

__all__ = [
    "LEADERBOARD_SCHEMA_VERSION",
    "WIDTH",
    "current_recipe",
    "format_leaderboard",
    "merge_reports",
    "slow_machine",
]

LEADERBOARD_SCHEMA_VERSION = "1.0"


def _find_reports(root: Path) -> list[Path]:
    return sorted(
        p for p in root.rglob("report.json") if "runs" not in p.relative_to(root).parts[:-1]
    )


def _budget(report: dict[str, Any]) -> str | None:
    """A measured row's training budget per model: ``"60 min"``, ``"2000 steps"`` or None,
    with ``" + refine 50 at lr 0.02"`` where the evaluation refined the slots
    (``--refine-slots 50 --refine-lr 0.02``), so that refined rows never replace the
    encoder's own, nor rows refined at another rate."""
    settings = report.get("scale_settings") or {}
    minutes, steps = settings.get("train_minutes"), settings.get("train_steps_override")
    if minutes is not None:
        budget: str | None = f"{minutes:g} min"
    else:
        budget = None if steps is None else f"{steps} steps"
    refine, lr = adapter.refinement_of(settings)
    if refine:
        return f"{budget or 'default'} + refine {refine} at lr {lr:g}"
    return budget


def _rank(entry: dict[str, Any]) -> tuple[bool, bool, bool, str]:
    """Order of preference of two rows with the same key: measured numbers, then the
    current recipe's model (or not known), then a model not trained on a machine slower
    than the recipe's (``slow_machine``: a minute budget gave it fewer steps), then newest."""
    has_value = any(v is not None for v in (entry.get("metrics") or {}).values())
    return (
        has_value,
        entry.get("current_recipe") is not False,
        not entry.get("slow_machine", False),
        entry["created_utc"],
    )


def slow_machine(report: dict[str, Any], row: dict[str, Any]) -> bool:
    """Whether a measured row's model is a recipe model trained under a minute budget
    on a machine slower than the recipe's (:func:`benchmark.row_import.recipe_rate_note`):
    its steps, not the recipe, set its numbers."""
    model = [m for m in report.get("models") or [] if m.get("run_key") == row.get("run_key")]
    return recipe_rate_note(model) is not None


#: Run fields that differ between runs of one recipe (the seed, the step limit).
_PER_RUN = ("seed", "steps")


def _jsonable(d: dict[str, Any]) -> dict[str, Any]:
    return json.loads(json.dumps(d))


def current_recipe(report: dict[str, Any], row: dict[str, Any]) -> bool | None:
    """Whether a measured row's model was trained with the configs that ``benchmark run``
    gives its full model today (the model config and the learning fields of the train
    config, seed and step limit aside). None where that cannot be told: not the full
    model, no model entry, or a scale or preset svorf does not know."""
    model = next(
        (m for m in report.get("models") or [] if m.get("run_key") == row.get("run_key")), None
    )
    if model is None or model.get("variant") != "full" or row.get("variant") != "full":
        return None
    try:
        mcfg, tcfg = adapter.base_configs(report["scale"], model["train_dataset"].split("/")[0])
    except (ValueError, KeyError):
        return None
    train_now = {k: v for k, v in adapter.learning_fields(tcfg).items() if k not in _PER_RUN}
    stored = model.get("train_config") or {}
    train_then = {k: stored.get(k) for k in train_now}
    return _jsonable(adapter.config_dict(mcfg)) == model.get("model_config") and _jsonable(
        train_now
    ) == _jsonable(train_then)


def merge_reports(root: str | os.PathLike, write: bool = True) -> dict[str, Any]:
    """Merge every valid ``report.json`` under ``root``.

    Args:
        root: Folder searched recursively (model run folders ``runs/`` are skipped).
        write: Also write ``root/leaderboard.json`` (atomically).

    Returns:
        ``{"schema_version", "created_utc", "reports": [...], "skipped": [...],
        "entries": [...]}``; each entry is a row plus ``protocol``, ``scale``,
        ``report`` (path relative to root), ``created_utc``, ``git_commit`` and
        ``device``. Paper rows appear once per (table, model, dataset).

    Raises:
        FileNotFoundError: If ``root`` is not a folder.
    """
    root = Path(root)
    if not root.is_dir():
        raise FileNotFoundError(f"leaderboard: {root} is not a folder")
    best: dict[tuple, dict[str, Any]] = {}
    reports, skipped = [], []
    for path in _find_reports(root):
        rel = str(path.relative_to(root))
        try:
            report = json.loads(path.read_text())
            validate_report(report)
        except (OSError, ValueError, SchemaError) as err:
            skipped.append({"report": rel, "reason": str(err)[:500]})
            continue
        reports.append(
            {
                "report": rel,
                "protocol": report["protocol"],
                "scale": report["scale"],
                "status": report["status"],
                "created_utc": report["created_utc"],
            }
        )
        for pos, row in enumerate(report["rows"]):
            src = row["source"]
            scale = None if src == "paper" else report["scale"]
            # Measured rows of different training seeds are different entries (a recipe is
            # judged at two seeds); baselines and paper rows do not depend on it.
            seed = report.get("seeds", {}).get("train") if src == "measured" else None
            # ... and so are rows of different training budgets (60 minutes, 2,000 steps).
            budget = _budget(report) if src == "measured" else None
            # A chance baseline is computed on the test scenes, so baselines on the scenes of
            # different data seeds are different entries too (K image blocks: 59.8 / 55.0).
            data_seed = report.get("seeds", {}).get("data") if src == "baseline" else None
            key = (
                None if src == "paper" else report["protocol"],
                scale,
                row["table"],
                row["model"],
                row["dataset"],
                src,
                seed,
                budget,
                data_seed,
            )
            entry = dict(row)
            entry.update(
                protocol=report["protocol"],
                scale=report["scale"] if src != "paper" else None,
                report=rel,
                created_utc=report["created_utc"],
                git_commit=report["git"].get("commit"),
                device=report["hardware"].get("device"),
                position=pos,
                seed=seed,
                budget=budget,
            )
            if data_seed is not None:
                entry["data_seed"] = data_seed
            if src == "measured":
                entry["current_recipe"] = current_recipe(report, row)
                if slow_machine(report, row):
                    entry["slow_machine"] = True
            # The newest row wins, except that a row without numbers (not trained, failed,
            # data unavailable) never replaces one with numbers, and a lever's (or an older
            # recipe's) model never replaces the current recipe's.
            old = best.get(key)
            if old is None or _rank(old) <= _rank(entry):
                best[key] = entry
    order = {t: i for i, t in enumerate(PAPER_TABLES)}
    src_order = {"paper": 0, "measured": 1, "baseline": 2}
    entries = sorted(
        best.values(),
        key=lambda e: (
            order.get(e["table"], len(order)),
            e["table"],
            e["dataset"],
            src_order[e["source"]],
            e.get("scale") or "",
            e["seed"] if e["seed"] is not None else e.get("data_seed", -1),
            e.get("budget") or "",
            e["position"],
        ),
    )
    board = {
        "schema_version": LEADERBOARD_SCHEMA_VERSION,
        "kind": "svorf-benchmark-leaderboard",
        "created_utc": utc_now(),
        "reports": reports,
        "skipped": skipped,
        "entries": entries,
    }
    if write:
        write_json(root / "leaderboard.json", board)
    return board


#: Widest line of the printed leaderboard (terminal columns).
WIDTH = 120
#: Model names longer than this are cut (with an ellipsis) in the printed table.
MODEL_WIDTH = 44


def _clip(text: str, width: int) -> str:
    return text if len(text) <= width else text[: width - 1] + "\u2026"


def _wrap(text: str, width: int, indent: str = "") -> list[str]:
    return textwrap.wrap(
        text, width, initial_indent=indent, subsequent_indent=indent + "  ", break_on_hyphens=False
    ) or [indent]


def _source(r: dict[str, Any]) -> str:
    """Who the row's numbers come from: ``paper``, ``cpu seed 0, 60 min`` (measured at a
    scale, training seed and budget per model; ``, earlier recipe`` where the model's
    configs are not the ones the recipe gives today; ``, slow machine`` where a minute
    budget's model trained slower than the recipe's) or ``cpu baseline, data 1`` (a chance
    baseline, on the test scenes of data seed 1)."""
    if r["source"] == "paper":
        return "paper"
    if r["source"] == "baseline":
        scenes = f", data {r['data_seed']}" if r.get("data_seed") is not None else ""
        return f"{r['scale']} baseline{scenes}"
    label = f"{r['scale']} seed {r['seed']}" if r.get("seed") is not None else str(r["scale"])
    label = f"{label}, {r['budget']}" if r.get("budget") else label
    label = f"{label}, slow machine" if r.get("slow_machine") else label
    return f"{label}, earlier recipe" if r.get("current_recipe") is False else label


def _grid(head: list[str], body: list[list[str]], right_from: int) -> list[str]:
    widths = [max(len(x) for x in col) for col in zip(head, *body, strict=True)]

    def line(cells: list[str]) -> str:
        out = [
            c.rjust(w) if i >= right_from else c.ljust(w)
            for i, (c, w) in enumerate(zip(cells, widths, strict=True))
        ]
        return "  ".join(out).rstrip()

    return [line(head), line(["-" * w for w in widths]), *(line(b) for b in body)]


def _chunks(widths: list[int], room: int) -> list[list[int]]:
    """Split metric columns (their widths) into runs that fit in ``room`` columns each."""
    out: list[list[int]] = [[]]
    used = 0
    for i, w in enumerate(widths):
        if out[-1] and used + 2 + w > room:
            out.append([])
            used = 0
        out[-1].append(i)
        used += 2 + w
    return out


def _null_notes(rows: list[dict[str, Any]], width: int) -> list[str]:
    """One line per (row, reason): which values are null and why, in words."""
    groups: dict[tuple[str, str, str, tuple[str, ...]], list[str]] = {}
    for r in rows:
        by_reason: dict[str, list[str]] = {}
        for m, why in sorted(r["null_reasons"].items()):
            if r["metrics"].get(m, 0) is None:
                by_reason.setdefault(reason_text(why), []).append(m)
        for why, ms in by_reason.items():
            what = (
                ("all metrics",)
                if len(ms) == len(r["metrics"]) and len(ms) > 1
                else tuple(metric_label(m) for m in ms)
            )
            key = (r["model"], _source(r), why, what)
            groups.setdefault(key, [])
            if r["dataset"] not in groups[key]:
                groups[key].append(r["dataset"])
    out = []
    for (model, src, why, what), datasets in groups.items():
        text = f"{NULL} {model} ({src}), {', '.join(what)} on {', '.join(datasets)}: {why}"
        out.append(_clip(text, width))
    return out


def _format_table(table: str, rows: list[dict[str, Any]], width: int) -> list[str]:
    metrics = metric_columns(table, rows)
    title = table_title(table)
    lines = [f"== {title} ==", *_wrap(table_description(table), width)]
    labels = [metric_label(m) for m in metrics]
    models = [_clip(r["model"], MODEL_WIDTH) for r in rows]
    sources = [_source(r) for r in rows]
    cells = [
        [fmt_metric(m, r["metrics"][m]) if m in r["metrics"] else "" for m in metrics] for r in rows
    ]
    key_w = max(len("model"), *map(len, models)) + 2 + max(len("source"), *map(len, sources))
    col_w = [max(len(labels[i]), *(len(c[i]) for c in cells)) for i in range(len(metrics))]
    parts = _chunks(col_w, width - key_w)
    for k, idx in enumerate(parts):
        if len(parts) > 1:
            lines.append(f"(part {k + 1} of {len(parts)} of the columns)")
        head = ["model", "source", *(labels[i] for i in idx)]
        body, groups = [], []
        for j, r in enumerate(rows):
            if k and not any(cells[j][i] for i in idx):
                continue  # later parts: only the rows with a value in these columns
            if not groups or groups[-1][0] != r["dataset"]:
                groups.append((r["dataset"], len(body)))
            body.append([models[j], sources[j], *(cells[j][i] for i in idx)])
        grid = _grid(head, body, right_from=2)
        lines.extend(grid[:2])
        starts = {pos: ds for ds, pos in groups}
        for pos, text in enumerate(grid[2:]):
            if pos in starts:
                lines.append(f"[{starts[pos]}]")
            lines.append(text)
        lines.append("")
    notes = _null_notes(rows, width)
    if notes:
        lines.append("Empty values (" + NULL + "):")
        lines.extend(notes)
        lines.append("")
    return lines


def format_leaderboard(board: dict[str, Any], width: int = WIDTH) -> str:
    """Plain-text tables, one per table: paper rows, then measured and baseline rows,
    grouped by test dataset; no line is wider than ``width``.

    Numbers use the paper's conventions (:mod:`benchmark.display`: ARI family on the
    0-100 scale with one decimal, PSNR in dB, SSIM / LPIPS with three decimals, times
    with units); metric columns that do not fit beside the model and source columns
    continue in a second part of the table.
    """
    tables: dict[str, list[dict[str, Any]]] = {}
    for e in board["entries"]:
        tables.setdefault(e["table"], []).append(e)
    lines: list[str] = []
    for table, rows in tables.items():
        # Paper-only tables are shown only when some report measured rows for them.
        if all(r["source"] == "paper" for r in rows):
            continue
        lines.extend(_format_table(table, rows, width))
    if lines:
        head = [
            *_wrap(LEGEND, width),
            *_wrap(
                "source: 'paper' = the paper's number; '<scale> seed N' = measured here at "
                "that scale with training seed N ('earlier recipe': a model whose configs "
                "are not the ones `benchmark run` gives today; 'slow machine': a minute "
                "budget's model trained at under 0.8x the recipe's steps per minute); "
                "'<scale> baseline, data N' = a "
                "chance baseline computed here on the test scenes of data seed N. An empty "
                "cell: the row has no such metric.",
                width,
            ),
            "",
        ]
        lines = head + lines
    if board["skipped"]:
        lines.append("Skipped reports:")
        for s in board["skipped"]:
            lines.extend(_wrap(f"{s['report']}: {s['reason']}", width, indent="  "))
    if not lines:
        lines.append("No measured rows found (no valid report.json under the folder).")
    return "\n".join(lines)
