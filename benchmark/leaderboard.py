"""Merge benchmark reports into ``leaderboard.json`` and print it beside the paper.

Where this sits: ``benchmark leaderboard DIR`` walks ``DIR`` for ``report.json``
files (every protocol writes one), validates each against the schema, keeps the
newest row per (protocol, scale, table, model, dataset, source, training seed of a
measured row), and writes
``DIR/leaderboard.json``. The printed table puts every measured and baseline
row under the paper's rows of the same table.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

from benchmark.html import fmt_value, metric_columns
from benchmark.paper_numbers import PAPER_TABLES
from benchmark.report import utc_now, write_json
from benchmark.schema import SchemaError, validate_report

__all__ = ["LEADERBOARD_SCHEMA_VERSION", "format_leaderboard", "merge_reports"]

LEADERBOARD_SCHEMA_VERSION = "1.0"


def _find_reports(root: Path) -> list[Path]:
    return sorted(
        p for p in root.rglob("report.json") if "runs" not in p.relative_to(root).parts[:-1]
    )


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
            key = (
                None if src == "paper" else report["protocol"],
                scale,
                row["table"],
                row["model"],
                row["dataset"],
                src,
                seed,
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
            )
            old = best.get(key)
            if old is None or old["created_utc"] <= entry["created_utc"]:
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
            e["seed"] if e["seed"] is not None else -1,
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


def format_leaderboard(board: dict[str, Any]) -> str:
    """Plain-text tables, one per paper table: paper rows, then measured and baseline rows."""
    tables: dict[str, list[dict[str, Any]]] = {}
    for e in board["entries"]:
        tables.setdefault(e["table"], []).append(e)
    # Show paper-only tables only if some report measured rows for them.
    lines = []
    for table, rows in tables.items():
        if all(r["source"] == "paper" for r in rows):
            continue
        metrics = metric_columns(table, rows)
        caption = PAPER_TABLES.get(table, {}).get("caption", "")
        lines.append(f"== {table}  {caption}")
        header = ["model", "dataset", "source", *metrics]
        body = []
        for r in rows:
            src = r["source"] if r["source"] == "paper" else f"{r['source']}/{r['scale']}"
            if r.get("seed") is not None:
                src += f" seed {r['seed']}"
            body.append(
                [
                    r["model"],
                    r["dataset"],
                    src,
                    *(fmt_value(r["metrics"].get(m), m) for m in metrics),
                ]
            )
        widths = [max(len(str(x)) for x in col) for col in zip(header, *body, strict=True)]
        fmt = "  ".join(f"{{:<{w}}}" for w in widths)
        lines.append(fmt.format(*header))
        lines.append(fmt.format(*("-" * w for w in widths)))
        lines.extend(fmt.format(*b) for b in body)
        lines.append("")
    if board["skipped"]:
        lines.append("Skipped reports:")
        lines.extend(f"  {s['report']}: {s['reason']}" for s in board["skipped"])
    if not lines:
        lines.append("No measured rows found (no valid report.json under the folder).")
    return "\n".join(lines)
