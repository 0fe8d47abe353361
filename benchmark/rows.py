"""The rows of a table protocol's report: measured, unavailable and chance-baseline rows,
and the plain-words verdict of whether a measured model decomposes the scenes.

Where this sits: a table protocol declares its rows as :class:`MeasuredRow`;
:func:`benchmark.runner.run_table_protocol` scores them (through
:class:`benchmark.context.Context`) and turns each result into a report :class:`Row` here
(``benchmark.report_row``, re-exported here: its :meth:`Row.to_dict` is the JSON the
report holds). Every row's id is :func:`row_id`, which the other protocols use too.

Measured rows with ARI / FG-ARI also carry the scene-shuffle control
(:data:`benchmark.evaluate.CONTROL_KEYS`), and :func:`verdicts_for` says a row
decomposes only if its FG-ARI beats both the chance baselines and that control.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from benchmark.datasets import DatasetInfo
from benchmark.evaluate import BASELINES, CONTROL_KEYS, EvalResult
from benchmark.jobs import ModelJob
from benchmark.report_row import Row, row_id
from benchmark.scales import ScaleSettings

__all__ = [
    "MeasuredRow",
    "Row",
    "chance_baseline_rows",
    "measured_row",
    "row_id",
    "row_metrics",
    "unavailable_row",
    "verdicts_for",
]


@dataclass(frozen=True)
class MeasuredRow:
    """A measured row of a paper table.

    Attributes:
        table: paper table id (``tab:ablation``...).
        model: the row's model name, as printed in the paper.
        dataset: the test preset.
        job: the model scored.
        metrics: metrics shown in the row (paper's columns first).
        baseline_metrics: metrics of the chance rows added for this table.
    """

    table: str
    model: str
    dataset: str
    job: ModelJob
    metrics: tuple[str, ...]
    note: str = ""


def row_metrics(spec: MeasuredRow) -> tuple[str, ...]:
    """The metrics of a measured row: the declared ones, plus the scene-shuffle control
    (:data:`CONTROL_KEYS`) when the row has ARI or FG-ARI."""
    if any(m in spec.metrics for m in ("ari", "fg_ari")):
        return tuple(dict.fromkeys(spec.metrics + CONTROL_KEYS))
    return tuple(spec.metrics)


def measured_row(
    spec: MeasuredRow, run_key: str, train_dataset: str, test: DatasetInfo, res: EvalResult
) -> Row:
    """The report row of ``spec``: the model ``run_key`` (trained on ``train_dataset``)
    scored on ``test`` (``res``), with the metrics of :func:`row_metrics` and a null reason
    for each missing one."""
    names = row_metrics(spec)
    metrics = {m: res.metrics.get(m) for m in names}
    reasons = {m: res.null_reasons.get(m, "not_computed") for m, v in metrics.items() if v is None}
    extra: dict[str, Any] = {
        "nan_counts": {m: res.nan_counts.get(m, 0) for m in names if m in res.nan_counts},
        "run_key": run_key,
        "train_dataset": train_dataset,
        "test_dataset": test.name,
        "test_fingerprint": test.fingerprint,
        "eval_wall_s": round(res.wall_s, 3),
    }
    if spec.note:
        extra["note"] = spec.note
    if res.details:
        extra["details"] = res.details
    return Row(
        table=spec.table,
        model=spec.model,
        dataset=spec.dataset,
        source="measured",
        metrics=metrics,
        null_reasons=reasons,
        variant=spec.job.variant,
        n_scenes=res.n_scenes,
        extra=extra,
    )


def unavailable_row(spec: MeasuredRow, why: str, kind: str = "dataset_unavailable") -> Row:
    """A measured row with every metric null: ``kind`` (``dataset_unavailable``,
    ``not_trained`` or ``failed``) and ``why`` are the reason."""
    reason = f"{kind}: " + why[:300]
    names = row_metrics(spec)
    extra = {"failed": why[:1000]} if kind == "failed" else {}
    return Row(
        table=spec.table,
        model=spec.model,
        dataset=spec.dataset,
        source="measured",
        metrics=dict.fromkeys(names),
        null_reasons=dict.fromkeys(names, reason),
        variant=spec.job.variant,
        n_scenes=0,
        extra={**extra, "train_dataset": f"{spec.job.train_preset}/train"},
    )


def chance_baseline_rows(
    table: str, dataset: str, metrics: tuple[str, ...], res: dict[str, EvalResult]
) -> list[Row]:
    """The chance rows (:data:`benchmark.evaluate.BASELINES`) of ``table`` on ``dataset``:
    each baseline's results ``res`` on the table's ``metrics`` it can score (image metrics
    for the flat colour, segmentation metrics for the others; never the control)."""
    rows = []
    image = {"psnr", "ssim", "lpips"}
    metrics = tuple(m for m in metrics if m not in CONTROL_KEYS)  # a model's own control
    for name, label in BASELINES.items():
        if name == "median_colour":
            keep = tuple(m for m in metrics if m in image)
        else:
            keep = tuple(m for m in metrics if m not in image and not m.startswith("depth_"))
        if not keep:
            continue
        r = res[name]
        m = {k: r.metrics.get(k) for k in keep}
        reasons = {k: r.null_reasons.get(k, "not_computed") for k, v in m.items() if v is None}
        rows.append(
            Row(
                table=table,
                model=label,
                dataset=dataset,
                source="baseline",
                metrics=m,
                null_reasons=reasons,
                n_scenes=r.n_scenes,
            )
        )
    return rows


def _best_chance(rows: list[dict[str, Any]], row: dict[str, Any], metric: str) -> float | None:
    """The best chance baseline's ``metric`` on ``row``'s table and test set (None: none)."""
    values = [
        b["metrics"][metric]
        for b in rows
        if b["source"] == "baseline"
        and b["table"] == row["table"]
        and b["dataset"] == row["dataset"]
        and b["metrics"].get(metric) is not None
    ]
    return max(values) if values else None


def verdicts_for(rows: list[dict[str, Any]], settings: ScaleSettings) -> list[dict[str, Any]]:
    """Say plainly, per measured row with FG-ARI, whether the model decomposes scenes.

    A row decomposes when all of these hold (T = ``settings.decompose_threshold``,
    M = ``settings.decompose_margin``):

    - FG-ARI >= T and >= the best chance baseline of its table and test set + M;
    - FG-ARI >= its own scene-shuffle control ``fg_ari_shuffled`` + M (the same model
      with another scene's slots: a segmentation that ignores the image, such as a
      fixed spatial tiling, scores about the same with them).

    ``decomposes`` is None when FG-ARI is null, or when the chance rule passes but the
    control is missing (null or absent from the row), since then it cannot be told.

    FG-ARI ignores background pixels, so a model whose slots each take an object *and* a
    share of the floor and walls around it can pass. ``background_split`` says so (it does
    not change ``decomposes``): True when the row's ARI (every pixel) is below the best
    chance baseline's ARI + M; the message of such a row then says that the background is
    divided among the slots. None when ARI or a chance ARI is missing.
    """
    margin = settings.decompose_margin
    out = []
    for r in rows:
        if r["source"] != "measured" or "fg_ari" not in r["metrics"]:
            continue
        fg = r["metrics"]["fg_ari"]
        best = _best_chance(rows, r, "fg_ari")
        best_ari = _best_chance(rows, r, "ari")
        ari = r["metrics"].get("ari")
        split: bool | None = None
        if ari is not None and best_ari is not None:
            split = ari < best_ari + margin
        paper = [
            p["metrics"].get("fg_ari")
            for p in rows
            if p["source"] == "paper"
            and p["table"] == r["table"]
            and p["dataset"] == r["dataset"]
            and p["model"] == r["model"]
        ]
        paper_txt = f"; paper {paper[0]:.1f}" if paper and paper[0] is not None else ""
        if fg is None:
            out.append(
                {
                    "table": r["table"],
                    "dataset": r["dataset"],
                    "model": r["model"],
                    "decomposes": None,
                    "message": "FG-ARI could not be computed ("
                    + r["null_reasons"].get("fg_ari", "?")
                    + ")",
                }
            )
            continue
        shuffled = r["metrics"].get("fg_ari_shuffled")
        beats_chance = fg >= settings.decompose_threshold and (best is None or fg >= best + margin)
        beats_control = shuffled is None or fg >= shuffled + margin
        chance_txt = (
            f"best chance baseline {best:.1f}" if best is not None else "no chance baseline"
        )
        failed = []
        if not beats_chance:
            failed.append(
                f"FG-ARI {fg:.1f} vs {chance_txt}{paper_txt} (threshold: FG-ARI >= "
                f"{settings.decompose_threshold:.0f} and >= chance + {margin:.0f})"
            )
        if not beats_control:
            failed.append(
                f"segmentation does not depend on the scene: FG-ARI {fg:.1f} vs "
                f"{shuffled:.1f} with another scene's slots (needs >= +{margin:.0f})"
            )
        ok: bool | None
        if failed:
            ok = False
            msg = f"does NOT decompose at scale '{settings.name}': " + "; ".join(failed) + "."
        elif shuffled is None:
            ok = None
            why = r["null_reasons"].get("fg_ari_shuffled", "not in this row")
            msg = (
                f"cannot say whether it decomposes: FG-ARI {fg:.1f} vs {chance_txt}{paper_txt} "
                f"passes the chance rule, but the scene-shuffle control (FG-ARI with another "
                f"scene's slots) is missing ({why})."
            )
        else:
            ok = True
            msg = (
                f"decomposes: FG-ARI {fg:.1f} vs {chance_txt} and {shuffled:.1f} with another "
                f"scene's slots{paper_txt}."
            )
            if split:
                msg += (
                    f" The background is not one slot: ARI {ari:.1f} (every pixel) vs best "
                    f"chance {best_ari:.1f} + {margin:.0f}: the slots divide the floor and walls "
                    f"among them, which FG-ARI does not score."
                )
        out.append(
            {
                "table": r["table"],
                "dataset": r["dataset"],
                "model": r["model"],
                "decomposes": ok,
                "fg_ari": fg,
                "chance_fg_ari": best,
                "fg_ari_shuffled": shuffled,
                "background_split": split,
                "message": msg,
            }
        )
    return out
