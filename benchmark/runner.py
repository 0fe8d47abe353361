"""The protocol engine: datasets -> cached models -> cached evaluations -> rows -> report.

Where this sits: ``benchmark run NAME`` builds a :class:`Context` and calls the
protocol's function (``benchmark.protocols``), which declares its rows with
:class:`ModelJob` / :class:`MeasuredRow` and hands them to :func:`run_table_protocol`.

Caching and resume (all writes atomic):

- models: ``<out>/runs/<key>/`` with ``key = hash(dataset fingerprint, model config,
  train config without bookkeeping fields, seed, adapter version[, training wall-time
  budget])``. svorf writes its checkpoints there and resumes an interrupted run (a
  budgeted run counts the time already trained); ``benchmark_run.json`` marks a
  finished one, which any later protocol with the same key reuses.
- evaluations: ``<out>/evals/<model key>-<test fingerprint>-<eval key>/result.json``
  (+ ``sample.npz`` for the qualitative figure), shared by protocols; the eval key
  includes :data:`benchmark.evaluate.EVAL_VERSION`, so a change in what an evaluation
  computes recomputes it (from the cached model).
- rows: ``<out>/<protocol>-<scale>/rows/<row id>.json``; a rerun skips finished rows
  whose test data, model key and evaluation version are still the ones this run would use.

Measured rows with ARI / FG-ARI also carry the scene-shuffle control
(:data:`benchmark.evaluate.CONTROL_KEYS`), and :func:`verdicts_for` says a row
decomposes only if its FG-ARI beats both the chance baselines and that control.

``--datasets`` (``Context.only_datasets``) keeps the measured and paper rows of the
named test datasets of a table protocol; the report's notes name the ones left out.
"""

from __future__ import annotations

import json
import math
import os
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from benchmark import adapter
from benchmark.datasets import DatasetInfo, dataset_dir, ensure_dataset
from benchmark.evaluate import (
    BASELINES,
    CONTROL_KEYS,
    EVAL_VERSION,
    EvalResult,
    evaluate_baselines,
)
from benchmark.generator_bridge import DatasetUnavailable
from benchmark.jobs import ModelJob, evaluate_run, read_eval, train_run, write_eval
from benchmark.log import log
from benchmark.metrics import lpips_weight_candidates
from benchmark.orderings import Ordering, check_orderings, orderings_summary
from benchmark.paper_numbers import PAPER_TABLES, paper_rows
from benchmark.report import RowStore, new_report, stable_hash, write_report
from benchmark.scales import ScaleSettings, get_scale
from scenefmt.cli_util import did_you_mean

__all__ = [
    "BACKENDS",
    "BUDGET_STEP_CAP",
    "Context",
    "MeasuredRow",
    "ModelJob",
    "ModelRecord",
    "evaluate_run",
    "read_eval",
    "row_id",
    "row_metrics",
    "run_table_protocol",
    "train_run",
    "verdicts_for",
    "write_eval",
]

#: TrainConfig fields that do not change what is learned (left out of the cache key).
_BOOKKEEPING = ("device", "log_every", "ckpt_every", "eval_every", "eval_scenes")

#: Step limit of a run with a wall-clock budget (``--train-minutes``) and no ``--steps``:
#: the budget is what stops it (as in ``python -m svorf.recipe train-eval --minutes``).
BUDGET_STEP_CAP = 1_000_000

#: Where a table protocol's jobs run (``--backend``).
BACKENDS = ("local", "ray")


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


@dataclass
class ModelRecord:
    """A trained model (run folder) and what it took."""

    key: str
    run_dir: Path
    job: ModelJob
    train_dataset: DatasetInfo
    model_config: dict[str, Any]
    train_config: dict[str, Any]
    seed: int
    reused: bool
    train_wall_s: float
    summary: dict[str, Any]
    config_source: str = ""
    train_budget_s: float | None = None

    @property
    def steps_done(self) -> int | None:
        """Optimizer steps the run finished (svorf's summary), None if unknown."""
        v = self.summary.get("steps")
        return int(v) if isinstance(v, (int, float)) and not isinstance(v, bool) else None

    def budget_report(self) -> dict[str, Any]:
        """Steps done, training wall time and what stopped the run."""
        cap = int(self.train_config.get("steps") or 0)
        done = self.steps_done
        return {
            "minutes": None if self.train_budget_s is None else self.train_budget_s / 60.0,
            "max_wall_s": self.train_budget_s,
            "step_limit": cap,
            "steps_done": done,
            "train_wall_s": float(self.train_wall_s),
            "stopped_by": None
            if done is None
            else ("steps" if done >= cap or self.train_budget_s is None else "time_budget"),
        }

    def to_report(self) -> dict[str, Any]:
        return {
            "run_key": self.key,
            "run_dir": str(self.run_dir),
            "variant": self.job.variant,
            "train_dataset": self.train_dataset.name,
            "train_dataset_fingerprint": self.train_dataset.fingerprint,
            "model_config": self.model_config,
            "train_config": self.train_config,
            "seed": self.seed,
            "reused": self.reused,
            "train_wall_s": float(self.train_wall_s),
            "steps_done": self.steps_done,
            "config_source": self.config_source,
            "train_budget": self.budget_report(),
            "init_from": self.summary.get("init_from"),
            "summary": self.summary,
        }


def row_id(table: str, model: str, dataset: str, source: str) -> str:
    """Stable id of a report row."""
    return f"{table}|{model}|{dataset}|{source}"


class Context:
    """Everything one protocol run shares: folders, scale, device, caches and timers.

    Args:
        protocol: protocol name.
        scale: ``smoke`` / ``cpu`` / ``paper``.
        out: the ``--out`` folder (reports, runs, evaluation cache).
        data: the ``--data`` folder (datasets).
        device: torch device string for training and evaluation.
        data_source: ``generator`` or ``synthetic`` (see :mod:`benchmark.datasets`).
        seed: base seed (data, training and evaluation seeds derive from it).
        progress: show progress bars.
        lpips_weights: optional LPIPS weight file.
        train_steps: override of the scale's training steps (None = the scale's, or
            :data:`BUDGET_STEP_CAP` with ``train_minutes``).
        train_minutes: training wall-clock budget per model in minutes (None = steps
            only); part of the model cache key and recorded in the report.
        only_datasets: test datasets a table protocol keeps (None = all of them);
            an unknown name is a ValueError when the protocol runs.
        backend: ``local`` (everything in this process) or ``ray``: a table protocol's
            dataset scenes, training runs and evaluations run as Ray tasks, keyed by
            their cache keys (:mod:`benchmark.ray_jobs`).
        address: Ray cluster address (``auto``, ``host:6379``, ``ray://host:10001``;
            None = ``RAY_ADDRESS``, else a new local instance); only with ``ray``.
        no_train: train nothing: rows whose model has no finished cached run get null
            metrics with the reason ``not_trained`` (``--no-train``: score the rows whose
            models an earlier run of the same settings trained).
    """

    def __init__(
        self,
        protocol: str,
        scale: str,
        out: str | os.PathLike,
        data: str | os.PathLike,
        *,
        device: str = "cpu",
        data_source: str = "generator",
        seed: int = 0,
        progress: bool = True,
        lpips_weights: str | None = None,
        train_steps: int | None = None,
        train_minutes: float | None = None,
        only_datasets: list[str] | tuple[str, ...] | None = None,
        backend: str = "local",
        address: str | None = None,
        no_train: bool = False,
    ) -> None:
        if backend not in BACKENDS:
            raise ValueError(f"--backend must be one of {', '.join(BACKENDS)}, got {backend!r}")
        if address is not None and backend != "ray":
            raise ValueError("--address is a Ray cluster address; pass it with --backend ray")
        self.backend = backend
        self.address = address
        #: Only reuse finished cached models; rows whose model is not trained stay null.
        self.no_train = bool(no_train)
        #: Model keys trained by this run outside this process (Ray workers).
        self.trained_elsewhere: set[str] = set()
        self.protocol = protocol
        self.settings: ScaleSettings = get_scale(scale)
        self.scale = scale
        self.out = Path(out)
        self.data = Path(data)
        self.device = device
        self.data_source = data_source
        self.seeds = {"data": int(seed), "train": int(seed), "eval": int(seed)}
        self.progress = progress
        self.lpips_weights = lpips_weights
        if train_minutes is not None and not (
            isinstance(train_minutes, (int, float)) and math.isfinite(train_minutes)
        ):
            raise ValueError(f"--train-minutes must be a positive number, got {train_minutes!r}")
        if train_minutes is not None and train_minutes <= 0:
            raise ValueError(f"--train-minutes must be a positive number, got {train_minutes!r}")
        if train_steps is not None and train_steps < 1:
            raise ValueError(f"--steps must be >= 1, got {train_steps}")
        self.train_minutes = None if train_minutes is None else float(train_minutes)
        if train_steps is not None:
            self.train_steps = train_steps
        elif self.train_minutes is not None:
            self.train_steps = BUDGET_STEP_CAP
        else:
            self.train_steps = self.settings.train_steps
        self.only_datasets = (
            None if only_datasets is None else tuple(dict.fromkeys(str(d) for d in only_datasets))
        )
        self.report_dir = self.out / f"{protocol}-{scale}"
        self.timers = {"data": 0.0, "training": 0.0, "evaluation": 0.0}
        self.datasets: dict[tuple[str, str], DatasetInfo] = {}
        self.models: dict[str, ModelRecord] = {}
        self.notes: list[str] = []
        self.t0 = time.perf_counter()

    # ------------------------------------------------------------------ data

    def dataset(self, preset: str, split: str) -> DatasetInfo:
        """The split folder (generated if missing), timed under ``data``."""
        k = (preset, split)
        if k not in self.datasets:
            t = time.perf_counter()
            where = dataset_dir(self.data, self.settings.name, preset, split)
            log(f"dataset {preset}/{split} ({self.scale}, source {self.data_source}): {where}")
            self.datasets[k] = ensure_dataset(
                self.data,
                self.settings,
                preset,
                split,
                source=self.data_source,
                seed=self.seeds["data"],
                progress=self.progress,
                backend=self.backend,
                address=self.address,
            )
            self.timers["data"] += time.perf_counter() - t
        return self.datasets[k]

    # ------------------------------------------------------------------ models

    def configs(self, job: ModelJob) -> tuple[Any, Any]:
        mcfg = adapter.model_config(self.scale, job.train_preset, job.variant)
        tcfg = adapter.train_config(
            self.scale,
            job.train_preset,
            job.variant,
            self.seeds["train"],
            self.device,
            self.train_steps,
        )
        return mcfg, tcfg

    @property
    def train_budget_s(self) -> float | None:
        """The training wall-time budget per model in seconds (None = steps only)."""
        return None if self.train_minutes is None else self.train_minutes * 60.0

    def model_key(self, job: ModelJob) -> tuple[str, dict[str, Any]]:
        """``(cache key, key source)`` of ``job``'s run (needs its training split)."""
        ds = self.dataset(job.train_preset, "train")
        mcfg, tcfg = self.configs(job)
        tdict = adapter.config_dict(tcfg)
        key_src: dict[str, Any] = {
            "adapter": adapter.ADAPTER_VERSION,
            "dataset": ds.fingerprint,
            "model": adapter.config_dict(mcfg),
            "train": {k: v for k, v in tdict.items() if k not in _BOOKKEEPING},
            "seed": self.seeds["train"],
        }
        if self.train_budget_s is not None:
            # Only when set, so that the keys of step-limited runs stay what they were.
            key_src["train_budget_s"] = self.train_budget_s
        init = self.init_job(job)
        if init is not None:  # only when set: other keys stay what they were
            key_src["init_from"] = self.model_key(init)[0]
        return stable_hash(key_src), key_src

    def init_job(self, job: ModelJob) -> ModelJob | None:
        """The model whose weights start ``job``'s training (svorf's ``PresetSpec.init_from``:
        the paper starts Room-Diverse from a CLEVR-567 model), None for most models."""
        pre = adapter.init_preset(job.train_preset)
        return None if pre is None else ModelJob("full", pre)

    def model(self, job: ModelJob, train: bool = True) -> ModelRecord | None:
        """Train ``job`` or reuse the cached run with the same key (timed under ``training``).

        With ``train=False`` only a finished cached run is returned (else None).
        """
        ds = self.dataset(job.train_preset, "train")
        mcfg, tcfg = self.configs(job)
        mdict, tdict = adapter.config_dict(mcfg), adapter.config_dict(tcfg)
        key, key_src = self.model_key(job)
        source = adapter.config_source(self.scale, job.train_preset, job.variant)
        if key in self.models:
            return self.models[key]
        run_dir = self.out / "runs" / key
        marker = run_dir / "benchmark_run.json"
        done = None
        if marker.is_file():
            try:
                done = json.loads(marker.read_text())
                if done.get("key_source") != json.loads(json.dumps(key_src)):
                    done = None
            except (OSError, ValueError):
                done = None
        if done is not None:
            fresh = key in self.trained_elsewhere  # trained by this run on Ray workers
            log(
                f"model {job.variant} on {job.train_preset}: "
                + ("trained on a Ray worker, run " if fresh else "reusing run ")
                + key
            )
            rec = ModelRecord(
                key,
                run_dir,
                job,
                ds,
                mdict,
                tdict,
                self.seeds["train"],
                not fresh,
                float(done.get("train_wall_s", 0.0)),
                done.get("summary", {}),
                source,
                self.train_budget_s,
            )
        elif not train:
            return None
        else:
            init = self.init_job(job)
            init_rec = None if init is None else self.model(init)
            if init_rec is not None:
                log(f"model {job.variant} on {job.train_preset}: starts from run {init_rec.key}")
            budget = (
                ""
                if self.train_minutes is None
                else f"{self.train_minutes:g} min of training wall time, up to "
            )
            log(
                f"model {job.variant} on {job.train_preset}: training run {key} "
                f"({budget}{tdict.get('steps')} steps; configs from {source})"
            )
            payload, wall = train_run(
                ds.path,
                run_dir,
                mcfg,
                tcfg,
                key=key,
                key_src=key_src,
                job=job,
                progress=self.progress,
                max_wall_s=self.train_budget_s,
                init_from=None if init_rec is None else init_rec.run_dir,
            )
            self.timers["training"] += wall
            train_wall = payload["train_wall_s"]
            summary = payload["summary"]
            rec = ModelRecord(
                key,
                run_dir,
                job,
                ds,
                mdict,
                tdict,
                self.seeds["train"],
                False,
                train_wall,
                summary,
                source,
                self.train_budget_s,
            )
        self.models[key] = rec
        return rec

    # ------------------------------------------------------------------ evaluation

    def _lpips_available(self) -> bool:
        return any(
            p is not None and p.is_file() for _, p in lpips_weight_candidates(self.lpips_weights)
        )

    def _eval_dir(self, kind: str, test: DatasetInfo, extra: dict[str, Any]) -> Path:
        ekey = stable_hash(
            {
                "adapter": adapter.ADAPTER_VERSION,
                "eval": EVAL_VERSION,
                "input_view": 0,
                "max_scenes": self.settings.eval_scenes,
                "lpips": self._lpips_available(),
                "seed": self.seeds["eval"],
                **extra,
            }
        )
        return self.out / "evals" / f"{kind}-{test.fingerprint[:16]}-{ekey}"

    def eval_dir(self, rec: ModelRecord, test: DatasetInfo) -> Path:
        """The evaluation cache folder of ``rec`` on ``test``."""
        return self._eval_dir(rec.key, test, {})

    def evaluation(self, rec: ModelRecord, test: DatasetInfo) -> EvalResult:
        """Score ``rec`` on ``test`` (cached on disk; timed under ``evaluation``)."""
        d = self.eval_dir(rec, test)
        cached = read_eval(d)
        if cached is not None:
            return cached
        log(f"evaluating run {rec.key} ({rec.job.variant}) on {test.name}")
        t = time.perf_counter()
        res = evaluate_run(
            rec.run_dir,
            test,
            d,
            image_size=rec.model_config.get("image_size"),
            device=self.device,
            max_scenes=self.settings.eval_scenes,
            lpips_weights=self.lpips_weights,
            progress=self.progress,
        )
        self.timers["evaluation"] += time.perf_counter() - t
        return res

    def baselines(self, test: DatasetInfo, num_slots: int) -> dict[str, EvalResult]:
        """Chance baselines on ``test`` (cached)."""
        d = self._eval_dir("baselines", test, {"num_slots": num_slots})
        out: dict[str, EvalResult] = {}
        for name in BASELINES:
            r = read_eval(d / name)
            if r is None:
                break
            out[name] = r
        else:
            return out
        t = time.perf_counter()
        ds = adapter.open_dataset(test.path)
        res = evaluate_baselines(
            ds,
            num_slots,
            input_view=0,
            max_scenes=self.settings.eval_scenes,
            seed=self.seeds["eval"],
            lpips_weights=self.lpips_weights,
        )
        self.timers["evaluation"] += time.perf_counter() - t
        for name, r in res.items():
            write_eval(d / name, r)
        return res

    def sample(self, rec: ModelRecord, test: DatasetInfo) -> dict[str, np.ndarray] | None:
        """Arrays of the first test scene of an evaluation (for the qualitative figure)."""
        p = self._eval_dir(rec.key, test, {}) / "sample.npz"
        if not p.is_file():
            return None
        with np.load(p) as z:
            return {k: z[k] for k in z.files}

    # ------------------------------------------------------------------ report

    def base_report(self) -> dict[str, Any]:
        rep = new_report(self.protocol, self.scale, self.device)
        rep["seeds"] = dict(self.seeds)
        rep["scale_settings"] = {
            "benchmark": self.settings.to_dict(),
            "train_steps_override": self.train_steps,
            "train_minutes": self.train_minutes,
            "data_source": self.data_source,
            "only_datasets": None if self.only_datasets is None else list(self.only_datasets),
            "backend": self.backend,
        }
        return rep

    def finish(self, report: dict[str, Any]) -> Path:
        """Fill datasets/models/wall times, validate, write ``report.json`` and ``index.html``."""
        from benchmark.html import write_index

        report["datasets"] = [d.to_report() for d in self.datasets.values()]
        report["models"] = [m.to_report() for m in self.models.values()]
        for d in self.datasets.values():
            if d.deviations:
                self.notes.append(
                    f"Dataset {d.name} ({d.path}) differs from the '{self.scale}' scale's "
                    f"nominal settings: {'; '.join(d.deviations)}. "
                    + (
                        "It was generated so in this run."
                        if d.generated_now
                        else "It was found complete on disk and is used as found"
                        + (" (checked with generators.verify)" if d.source == "generator" else "")
                        + "; delete the folder to generate the nominal split."
                    )
                )
        on_recipe = [
            m for m in self.models.values() if m.config_source == adapter.RECIPE_CONFIG_SOURCE
        ]
        recipe = sorted({f"{m.job.variant} on {m.job.train_preset}" for m in on_recipe})
        if recipe:
            self.notes.append(
                f"The '{self.scale}' scale trains the CLEVR-567-family models with the cpu "
                f"recipe (svorf.train.CPU_RECIPE, docs/notes/cpu_recipe.md): {', '.join(recipe)}; "
                "the ablation variants are applied on top of it."
            )
        for m in self.models.values():
            base, _ = adapter.base_configs(self.scale, m.job.train_preset, m.job.variant)
            for note in adapter.variant_adjustments(base, m.job.variant)[1]:
                if note not in self.notes:
                    self.notes.append(f"Changed for the ablation on {m.job.train_preset}: {note}")
        if self.train_minutes is not None and self.models:
            done = "; ".join(
                f"{m.job.variant} on {m.job.train_preset}: {m.steps_done} steps in "
                f"{m.train_wall_s / 60.0:.1f} min (stopped by {m.budget_report()['stopped_by']})"
                for m in self.models.values()
            )
            self.notes.append(
                f"Training budget: {self.train_minutes:g} min of training wall time per model "
                f"(evaluation and checkpoint writes excluded), up to {self.train_steps} steps. "
                f"{done}. Steps done depend on the machine's speed and load, so a budgeted "
                "run is not reproducible step for step."
            )
        if self.data_source == "synthetic":
            self.notes.append(
                "Datasets are svorf.synthetic analytic sphere scenes (a stand-in for the "
                "Blender presets, used for tests); numbers are not comparable to the paper."
            )
        report["notes"] = list(dict.fromkeys(report.get("notes", []) + self.notes))
        report["wall_time_s"] = {
            **{k: round(v, 3) for k, v in self.timers.items()},
            "total": round(time.perf_counter() - self.t0, 3),
        }
        path = self.report_dir / "report.json"
        write_report(path, report)
        write_index(self.report_dir, report)
        return path  # `benchmark run` prints it (and index.html) once, at the end


# ---------------------------------------------------------------------- table protocols


def row_metrics(spec: MeasuredRow) -> tuple[str, ...]:
    """The metrics of a measured row: the declared ones, plus the scene-shuffle control
    (:data:`CONTROL_KEYS`) when the row has ARI or FG-ARI."""
    if any(m in spec.metrics for m in ("ari", "fg_ari")):
        return tuple(dict.fromkeys(spec.metrics + CONTROL_KEYS))
    return tuple(spec.metrics)


def _measured_row(
    spec: MeasuredRow, rec: ModelRecord, test: DatasetInfo, res: EvalResult
) -> dict[str, Any]:
    names = row_metrics(spec)
    metrics = {m: res.metrics.get(m) for m in names}
    reasons = {m: res.null_reasons.get(m, "not_computed") for m, v in metrics.items() if v is None}
    row = {
        "id": row_id(spec.table, spec.model, spec.dataset, "measured"),
        "table": spec.table,
        "model": spec.model,
        "dataset": spec.dataset,
        "variant": spec.job.variant,
        "source": "measured",
        "metrics": metrics,
        "null_reasons": reasons,
        "n_scenes": res.n_scenes,
        "nan_counts": {m: res.nan_counts.get(m, 0) for m in names if m in res.nan_counts},
        "run_key": rec.key,
        "train_dataset": rec.train_dataset.name,
        "test_dataset": test.name,
        "test_fingerprint": test.fingerprint,
        "eval_wall_s": round(res.wall_s, 3),
    }
    if spec.note:
        row["note"] = spec.note
    if res.details:
        row["details"] = res.details
    return row


def _unavailable_row(
    spec: MeasuredRow, why: str, kind: str = "dataset_unavailable"
) -> dict[str, Any]:
    """A measured row with every metric null: ``kind`` (``dataset_unavailable`` or
    ``failed``) and ``why`` are the reason."""
    reason = f"{kind}: " + why[:300]
    names = row_metrics(spec)
    extra = {"failed": why[:1000]} if kind == "failed" else {}
    return {
        **extra,
        "id": row_id(spec.table, spec.model, spec.dataset, "measured"),
        "table": spec.table,
        "model": spec.model,
        "dataset": spec.dataset,
        "variant": spec.job.variant,
        "source": "measured",
        "metrics": {m: None for m in names},
        "null_reasons": {m: reason for m in names},
        "n_scenes": 0,
        "train_dataset": f"{spec.job.train_preset}/train",
    }


def _baseline_rows(
    table: str, dataset: str, metrics: tuple[str, ...], res: dict[str, EvalResult]
) -> list[dict[str, Any]]:
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
        rows.append(
            {
                "id": row_id(table, label, dataset, "baseline"),
                "table": table,
                "model": label,
                "dataset": dataset,
                "variant": None,
                "source": "baseline",
                "metrics": m,
                "null_reasons": {
                    k: r.null_reasons.get(k, "not_computed") for k, v in m.items() if v is None
                },
                "n_scenes": r.n_scenes,
            }
        )
    return rows


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
    """
    margin = settings.decompose_margin
    out = []
    for r in rows:
        if r["source"] != "measured" or "fg_ari" not in r["metrics"]:
            continue
        fg = r["metrics"]["fg_ari"]
        chance = [
            b["metrics"].get("fg_ari")
            for b in rows
            if b["source"] == "baseline"
            and b["table"] == r["table"]
            and b["dataset"] == r["dataset"]
            and b["metrics"].get("fg_ari") is not None
        ]
        best = max(chance) if chance else None
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
        out.append(
            {
                "table": r["table"],
                "dataset": r["dataset"],
                "model": r["model"],
                "decomposes": ok,
                "fg_ari": fg,
                "chance_fg_ari": best,
                "fg_ari_shuffled": shuffled,
                "message": msg,
            }
        )
    return out


def _filter_datasets(
    ctx: Context, measured: list[MeasuredRow]
) -> tuple[list[MeasuredRow], set[str] | None, list[str]]:
    """Apply ``ctx.only_datasets``: ``(kept rows, kept test datasets or None, left out)``.

    Raises:
        ValueError: a name that is not a test dataset of this protocol (one line,
            naming the valid ones).
    """
    if ctx.only_datasets is None:
        return measured, None, []
    known = list(dict.fromkeys(s.dataset for s in measured))
    unknown = [d for d in ctx.only_datasets if d not in known]
    if not ctx.only_datasets:
        raise ValueError(
            f"--datasets: no dataset name (none given); choose from {', '.join(known)}"
        )
    if unknown:  # the first one, with "did you mean" and the valid names
        raise ValueError(
            f"--datasets: protocol {ctx.protocol!r} has no test dataset {unknown[0]!r}"
            f"{did_you_mean(unknown[0], known)} (choose from {', '.join(known)})"
        )
    keep = set(ctx.only_datasets)
    return [s for s in measured if s.dataset in keep], keep, [d for d in known if d not in keep]


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
        "lpips": ctx._lpips_available(),
    }
    store = RowStore(ctx.report_dir / "rows", store_ctx)
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
            ctx.dataset(spec.job.train_preset, "train")
        except DatasetUnavailable as err:
            log(f"row {spec.table} / {spec.model} / {spec.dataset}: dataset unavailable: {err}")
            unavailable.append(f"{spec.table} / {spec.model} / {spec.dataset}: {err}")
            rows.append(_unavailable_row(spec, str(err)))
            continue
        state["tests"][spec.dataset] = test
        stored = store.get(rid)
        if (
            stored is not None
            and stored.get("test_fingerprint") == test.fingerprint
            and stored.get("run_key") == ctx.model_key(spec.job)[0]
            and set(stored.get("metrics", {})) == set(row_metrics(spec))  # same columns
        ):
            log(f"row done, skipped: {spec.table} / {spec.model} / {spec.dataset}")
            skipped += 1
            rows.append(stored)
            # Keep the model in the report if its run is still on disk (never retrain here).
            rec = ctx.model(spec.job, train=False)
            if rec is not None:
                state["records"][(spec.job, spec.dataset)] = rec
            continue
        try:
            rec = ctx.model(spec.job, train=not ctx.no_train)
            if rec is None:  # --no-train and no finished cached run
                why = (
                    f"--no-train: no finished run of model {spec.job.variant} on "
                    f"{spec.job.train_preset} with these settings; run the same command "
                    "without --no-train to train it"
                )
                not_trained.append(f"{spec.table} / {spec.model} / {spec.dataset}")
                rows.append(_unavailable_row(spec, why, kind="not_trained"))
                continue
            res = ctx.evaluation(rec, test)
        except Exception as err:  # noqa: BLE001 - one failing row must not lose the others
            why = f"{type(err).__name__}: {err}".splitlines()[0]
            log(f"row {spec.table} / {spec.model} / {spec.dataset}: FAILED: {why}")
            failed.append(f"{spec.table} / {spec.model} / {spec.dataset}: {why}")
            rows.append(_unavailable_row(spec, why, kind="failed"))
            continue
        row = _measured_row(spec, rec, test, res)
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
        rows.extend(_baseline_rows(spec.table, spec.dataset, metrics, ctx.baselines(test, k_slots)))
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
            "Rows not trained in this run (--no-train; metrics null, reason 'not_trained'): "
            + "; ".join(not_trained)
        )
    if unavailable:
        report["status"] = "partial"
        ctx.notes.append(
            "Rows without data (metrics null, reason 'dataset_unavailable'): "
            + "; ".join(unavailable)
        )
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
        report["orderings"] = check_orderings(rows, orderings)
        ctx.notes.append(orderings_summary(report["orderings"]))
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
    ctx.notes.extend(ctx.settings.notes)
    return ctx.finish(report)


def finite(x: Any) -> bool:
    return isinstance(x, (int, float)) and math.isfinite(x)
