"""The run context of a protocol: folders, scale, device, seeds, and the cached datasets,
models and evaluations every protocol shares.

Where this sits: ``benchmark run NAME`` builds a :class:`Context` and hands it to the
protocol's function (:mod:`benchmark.protocols`); table protocols then go through
:func:`benchmark.runner.run_table_protocol`. The work itself is in :mod:`benchmark.jobs`
(training, evaluation) and :mod:`benchmark.datasets`; this module decides what is cached
where, and writes the report's common parts (:meth:`Context.base_report`,
:meth:`Context.finish`).

Caching and resume (all writes atomic):

- models: ``<out>/runs/<key>/`` with ``key = hash(dataset fingerprint, model config,
  train config without bookkeeping fields (``adapter.learning_fields``), seed, adapter
  version[, training wall-time budget])``: svorf's config key (``svorf config``) plus the
  data, so :meth:`Context.config_key` names the same model as ``svorf train``. svorf writes its checkpoints there and resumes an interrupted run (a
  budgeted run counts the time already trained); ``benchmark_run.json`` marks a
  finished one, which any later protocol with the same key reuses.
- evaluations: ``<out>/evals/<model key>-<test fingerprint>-<eval key>/result.json``
  (+ ``sample.npz`` for the qualitative figure), shared by protocols; the eval key
  includes :data:`benchmark.evaluate.EVAL_VERSION`, so a change in what an evaluation
  computes recomputes it (from the cached model).
"""

from __future__ import annotations

import json
import math
import os
import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from benchmark import adapter
from benchmark.datasets import (
    DatasetInfo,
    at_resolution,
    dataset_dir,
    ensure_dataset,
    split_state,
)
from benchmark.evaluate import BASELINES, EVAL_VERSION, EvalResult, evaluate_baselines
from benchmark.jobs import ModelJob, evaluate_run, read_eval, train_run, write_eval
from benchmark.log import log
from benchmark.metrics import lpips_weight_candidates
from benchmark.orderings import other_seed_rows
from benchmark.report import new_report, stable_hash, write_report
from benchmark.row_import import read_reports, recipe_rate_note, step_rate_note
from benchmark.scales import ScaleSettings, get_scale
from scenefmt.cli_util import did_you_mean

__all__ = ["BACKENDS", "BUDGET_STEP_CAP", "Context", "ModelRecord"]

#: Step limit of a run with a wall-clock budget (``--train-minutes``) and no ``--steps``:
#: the budget is what stops it (as in ``python -m benchmark.tools.recipe train-eval --minutes``).
BUDGET_STEP_CAP = 1_000_000

#: Where a table protocol's jobs run (``--backend``).
BACKENDS = ("local", "ray")


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

    @property
    def weights_scored(self) -> str:
        """The weights the evaluation scores (``svorf.checkpoint.load_run``'s "auto"):
        "ema", the moving average of a run trained with ``ema_decay``, else "raw"."""
        return "ema" if float(self.train_config.get("ema_decay") or 0.0) > 0.0 else "raw"

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
        """The record as the report's ``models`` entry."""
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
            "weights_scored": self.weights_scored,
            "config_source": self.config_source,
            "train_budget": self.budget_report(),
            "init_from": self.summary.get("init_from"),
            "summary": self.summary,
        }


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
        train_only: model variants (``full``, ``wo_nvs``, ...) this run may train (None =
            every one); the other rows are scored only if an earlier run trained their
            model, as with ``no_train`` (``--train-only``: build a table over several
            runs, the models that matter most first).
        rows_from: earlier ``report.json`` files (or their folders) whose measured rows a
            table protocol takes instead of recomputing them, where model key, test data
            and row context match (``--rows-from``; :mod:`benchmark.row_import`).
        spread_from: reports of the same protocol, scale and budget at other seeds; the
            orderings then give the seed-to-seed spread of each margin (``--spread-from``;
            :func:`benchmark.orderings.other_seed_rows`).
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
        train_only: list[str] | tuple[str, ...] | None = None,
        rows_from: list[str] | tuple[str, ...] | None = None,
        refine_slots: int = 0,
        refine_lr: float | None = None,
        spread_from: list[str] | tuple[str, ...] | None = None,
    ) -> None:
        if backend not in BACKENDS:
            raise ValueError(f"--backend must be one of {', '.join(BACKENDS)}, got {backend!r}")
        if address is not None and backend != "ray":
            raise ValueError("--address is a Ray cluster address; pass it with --backend ray")
        self.backend = backend
        self.address = address
        if isinstance(refine_slots, bool) or not isinstance(refine_slots, int) or refine_slots < 0:
            raise ValueError(f"--refine-slots must be a whole number >= 0, got {refine_slots!r}")
        #: Test-time slot refinement steps of every evaluation (0 = the encoder's slots).
        self.refine_slots = refine_slots
        if refine_lr is not None:
            if not refine_slots:
                raise ValueError("--refine-lr sets the rate of --refine-slots N; pass that too")
            if isinstance(refine_lr, bool) or not (
                isinstance(refine_lr, (int, float)) and math.isfinite(refine_lr) and refine_lr > 0
            ):
                raise ValueError(f"--refine-lr must be a positive number, got {refine_lr!r}")
        #: The slots' Adam learning rate of that refinement (None without refinement).
        self.refine_lr: float | None = None
        if refine_slots:
            self.refine_lr = adapter.default_refine_lr() if refine_lr is None else float(refine_lr)
        #: Only reuse finished cached models; rows whose model is not trained stay null.
        self.no_train = bool(no_train)
        if train_only is not None:
            from benchmark.adapter import VARIANTS

            train_only = tuple(dict.fromkeys(str(v).strip() for v in train_only if str(v).strip()))
            unknown = [v for v in train_only if v not in VARIANTS]
            if not train_only:
                raise ValueError(
                    f"--train-only: no model variant given (choose from {', '.join(VARIANTS)})"
                )
            if unknown:
                raise ValueError(
                    f"--train-only: no model variant {unknown[0]!r}"
                    f"{did_you_mean(unknown[0], list(VARIANTS))} (choose from {', '.join(VARIANTS)})"
                )
            if no_train:
                raise ValueError("--train-only and --no-train: pass one of them, not both")
        #: The model variants this run may train (None = all).
        self.train_only = train_only
        #: ``(path, report)`` of the ``--rows-from`` reports (read now: a bad path fails
        #: before any work).
        self.rows_from = read_reports(tuple(rows_from or ()))
        if self.rows_from and backend == "ray":
            raise ValueError(
                "--rows-from works with the local backend only; drop --backend ray, or run "
                "the rows it should take from the reports' own --out folder"
            )
        #: Model entries of the rows taken from ``rows_from`` (run key -> report entry).
        self.imported_models: dict[str, dict[str, Any]] = {}
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
        suffix = f"-refine{refine_slots}" if refine_slots else ""
        if refine_slots and self.refine_lr != adapter.default_refine_lr():
            suffix += f"-lr{self.refine_lr:g}"
        self.report_dir = self.out / f"{protocol}-{scale}{suffix}"
        spread = read_reports(tuple(spread_from or ()), "--spread-from")
        #: ``--spread-from`` report paths and their rows by seed (checked now: a report of
        #: another protocol, scale or budget fails before any work).
        self.spread_from = [p for p, _ in spread]
        self.seed_rows = other_seed_rows(
            spread,
            protocol=protocol,
            scale=scale,
            seed=int(seed),
            settings={
                "train_steps_override": self.train_steps,
                "train_minutes": self.train_minutes,
                "refine_slots": refine_slots,
                "refine_lr": self.refine_lr,
            },
        )
        self.timers = {"data": 0.0, "training": 0.0, "evaluation": 0.0}
        self.datasets: dict[tuple[str, str], DatasetInfo] = {}
        self.models: dict[str, ModelRecord] = {}
        self.notes: list[str] = []
        self.t0 = time.perf_counter()

    # ------------------------------------------------------------------ data

    def select_datasets(self, known: list[str] | tuple[str, ...]) -> tuple[list[str], list[str]]:
        """Apply ``--datasets`` (:attr:`only_datasets`) to a protocol's test datasets.

        Args:
            known: the protocol's test datasets, in its order.

        Returns:
            ``(kept, left_out)``, both in the order of ``known``; everything is kept
            without ``--datasets``.

        Raises:
            ValueError: ``--datasets`` names none, or a name that is not in ``known``
                (one line: "did you mean", and the valid names). Raised before any
                dataset is generated.
        """
        known = list(dict.fromkeys(known))
        if self.only_datasets is None:
            return known, []
        if not self.only_datasets:
            raise ValueError(
                f"--datasets: no dataset name (none given); choose from {', '.join(known)}"
            )
        unknown = [d for d in self.only_datasets if d not in known]
        if unknown:  # the first one, with "did you mean" and the valid names
            raise ValueError(
                f"--datasets: protocol {self.protocol!r} has no test dataset {unknown[0]!r}"
                f"{did_you_mean(unknown[0], known)} (choose from {', '.join(known)})"
            )
        keep = set(self.only_datasets)
        return [d for d in known if d in keep], [d for d in known if d not in keep]

    def dataset(self, preset: str, split: str, resolution: int | None = None) -> DatasetInfo:
        """The split folder (generated if missing), timed under ``data``; at ``resolution``
        instead of the scale's when given (:func:`benchmark.datasets.at_resolution`)."""
        settings = at_resolution(self.settings, resolution)
        k = self._dataset_key(preset, split, settings)
        if k not in self.datasets:
            t = time.perf_counter()
            where = dataset_dir(self.data, settings.name, preset, split)
            log(f"dataset {preset}/{split} ({settings.name}, source {self.data_source}): {where}")
            self.datasets[k] = ensure_dataset(
                self.data,
                settings,
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

    def _dataset_key(self, preset: str, split: str, settings: ScaleSettings) -> tuple[Any, ...]:
        """Where :meth:`dataset` keeps a split of these ``settings`` in ``self.datasets``."""
        if settings is self.settings:
            return (preset, split)
        return (preset, split, settings.resolution)

    def train_dataset(self, job: ModelJob) -> DatasetInfo:
        """``job``'s training split: the scale's, or the same scenes at the finer
        resolution its ``TrainConfig.target_size`` asks for."""
        return self.dataset(job.train_preset, "train", self.train_resolution(job))

    def train_resolution(self, job: ModelJob) -> int | None:
        """The resolution ``job``'s training asks of its split (None: the scale's)."""
        return getattr(self.configs(job)[1], "target_size", None)

    # ------------------------------------------------------------------ models

    def configs(self, job: ModelJob) -> tuple[Any, Any]:
        """``(ModelConfig, TrainConfig)`` of ``job`` at this scale, seed, device and steps."""
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
        key_src = self._key_source(job, self.train_dataset(job).fingerprint)
        return stable_hash(key_src), key_src

    def _key_source(self, job: ModelJob, fingerprint: str | None) -> dict[str, Any]:
        """What :meth:`model_key` hashes, with the training split's ``fingerprint``."""
        mcfg, tcfg = self.configs(job)
        key_src: dict[str, Any] = {
            "adapter": adapter.ADAPTER_VERSION,
            "dataset": fingerprint,
            "model": adapter.config_dict(mcfg),
            "train": adapter.learning_fields(tcfg),
            "seed": self.seeds["train"],
        }
        if self.train_budget_s is not None:
            # Only when set, so that the keys of step-limited runs stay what they were.
            key_src["train_budget_s"] = self.train_budget_s
        init = self.init_job(job)
        if init is not None:  # only when set: other keys stay what they were
            key_src["init_from"] = self.model_key(init)[0]
        return key_src

    def no_cached_run(self, job: ModelJob) -> bool:
        """True when no finished run in ``<out>/runs`` can be ``job``'s model and its
        training split is not on disk: a run that may not train it then needs neither
        (generating 1,000 scenes only to hash them would find nothing). A run whose marker
        names another training preset is not a match, even with the same settings. Runs
        started from another model's weights are always looked up the full way."""
        if self.init_job(job) is not None:
            return False
        settings = at_resolution(self.settings, self.train_resolution(job))
        if self._dataset_key(job.train_preset, "train", settings) in self.datasets:
            return False
        state = split_state(
            self.data,
            settings,
            job.train_preset,
            "train",
            source=self.data_source,
            seed=self.seeds["data"],
        )
        if state.usable:
            return False
        want = json.loads(json.dumps({**self._key_source(job, None), "dataset": None}))
        for marker in sorted((self.out / "runs").glob("*/benchmark_run.json")):
            try:
                payload = json.loads(marker.read_text())
            except (OSError, ValueError):
                continue
            if not isinstance(payload, dict):
                continue
            src, made_for = payload.get("key_source"), payload.get("job")
            if isinstance(made_for, dict) and made_for.get("train_preset") != job.train_preset:
                continue  # the same settings trained on another preset's split
            if isinstance(src, dict) and {**src, "dataset": None} == want:
                return False
        return True

    def config_key(self, job: ModelJob) -> str:
        """svorf's config key of ``job`` (``svorf.train_config.config_key``): what ``svorf
        config`` prints for the same model and schedule. Needs no data (the run key adds
        the dataset's fingerprint)."""
        mcfg, tcfg = self.configs(job)
        return adapter.config_key(mcfg, tcfg)

    def svorf_command(self, job: ModelJob) -> str | None:
        """The ``svorf train`` command line that trains the same model as ``job`` (the same
        :meth:`config_key`), or None where svorf has no preset for it (ablation variants)."""
        preset = adapter.svorf_preset(job.train_preset, job.variant)
        mcfg, tcfg = adapter.base_configs(self.scale, job.train_preset, job.variant)
        changes: dict[str, Any] = {"seed": self.seeds["train"]}
        if self.train_steps is not None:
            changes["steps"] = int(self.train_steps)
        if adapter.config_key(mcfg, replace(tcfg, **changes)) != self.config_key(job):
            return None
        where = at_resolution(self.settings, self.train_resolution(job)).name
        data = dataset_dir(self.data, where, job.train_preset, "train")
        words = ["svorf train", f"--scale {self.scale}", f"--preset {preset}", f"--data {data}"]
        if self.train_steps is not None:
            words.append(f"--steps {self.train_steps}")
        if self.seeds["train"]:
            words.append(f"--seed {self.seeds['train']}")
        if self.train_minutes is not None:
            words.append(f"--minutes {self.train_minutes:g}")
        init = self.init_job(job)
        if init is not None:
            words.append(f"--init-from <run of {init.variant} on {init.train_preset}>")
        return " ".join([*words, "--out RUN"])

    def init_job(self, job: ModelJob) -> ModelJob | None:
        """The model whose weights start ``job``'s training (svorf's ``PresetSpec.init_from``:
        the paper starts Room-Diverse from a CLEVR-567 model), None for most models."""
        pre = adapter.init_preset(job.train_preset)
        return None if pre is None else ModelJob("full", pre)

    def may_train(self, job: ModelJob) -> bool:
        """Whether this run may train ``job``'s model (``--no-train``, ``--train-only``)."""
        if self.no_train:
            return False
        return self.train_only is None or job.variant in self.train_only

    def not_trained_why(self, job: ModelJob) -> str:
        """Why a row of ``job`` has no model (``may_train`` was False, none was cached)."""
        flag = "--no-train" if self.no_train else f"--train-only {','.join(self.train_only or ())}"
        return (
            f"{flag}: no finished run of model {job.variant} on {job.train_preset} with these "
            f"settings; run the same command without {flag.split()[0]} to train it"
        )

    def model(self, job: ModelJob, train: bool = True) -> ModelRecord | None:
        """Train ``job`` or reuse the cached run with the same key (timed under ``training``).

        With ``train=False`` only a finished cached run is returned (else None); its
        training split is generated only where a run in ``<out>/runs`` may be it.
        """
        if not train and self.no_cached_run(job):
            return None
        ds = self.train_dataset(job)
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

    def lpips_available(self) -> bool:
        """Whether LPIPS weights are found locally (part of the evaluation cache key)."""
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
                "lpips": self.lpips_available(),
                "seed": self.seeds["eval"],
                **extra,
            }
        )
        return self.out / "evals" / f"{kind}-{test.fingerprint[:16]}-{ekey}"

    def eval_dir(self, rec: ModelRecord, test: DatasetInfo) -> Path:
        """The evaluation cache folder of ``rec`` on ``test`` (with ``--refine-slots``
        its own: only then, so that the caches of earlier runs keep their keys)."""
        return self._eval_dir(rec.key, test, self.refine_context())

    def refine_context(self) -> dict[str, Any]:
        """What test-time refinement adds to the evaluation cache key and the row context:
        nothing for the encoder's slots, the steps, and the rate where it is not
        :data:`benchmark.adapter.REFINE_LR_UNRECORDED` (so that the caches and rows of
        refinements at that rate, written before it was recorded, keep their keys)."""
        if not self.refine_slots:
            return {}
        extra: dict[str, Any] = {"refine_slots": self.refine_slots}
        if self.refine_lr != adapter.REFINE_LR_UNRECORDED:
            extra["refine_lr"] = self.refine_lr
        return extra

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
            refine_steps=self.refine_slots,
            refine_lr=self.refine_lr,
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
        p = self.eval_dir(rec, test) / "sample.npz"
        if not p.is_file():
            return None
        with np.load(p) as z:
            return {k: z[k] for k in z.files}

    # ------------------------------------------------------------------ report

    def base_report(self) -> dict[str, Any]:
        """A new report of this protocol with the run's seeds and scale settings."""
        rep = new_report(self.protocol, self.scale, self.device)
        rep["seeds"] = dict(self.seeds)
        rep["scale_settings"] = {
            "benchmark": self.settings.to_dict(),
            "train_steps_override": self.train_steps,
            "train_minutes": self.train_minutes,
            "data_source": self.data_source,
            "only_datasets": None if self.only_datasets is None else list(self.only_datasets),
            "train_only": None if self.train_only is None else list(self.train_only),
            "backend": self.backend,
            "refine_slots": self.refine_slots,
            "refine_lr": self.refine_lr,
        }
        return rep

    def finish(self, report: dict[str, Any]) -> Path:
        """Fill datasets/models/wall times, validate, write ``report.json`` and ``index.html``."""
        from benchmark.html import write_index

        report["datasets"] = [d.to_report() for d in self.datasets.values()]
        report["models"] = [m.to_report() for m in self.models.values()] + [
            m for k, m in self.imported_models.items() if k not in self.models
        ]
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
                f"The '{self.scale}' scale trains the CLEVR-567-family and Room-Chair models with the cpu "
                f"recipe (svorf.registry, docs/notes/cpu_recipe.md): {', '.join(recipe)}; "
                "the ablation variants are applied on top of it."
            )
        for m in self.models.values():
            base, _ = adapter.base_configs(self.scale, m.job.train_preset, m.job.variant)
            for note in adapter.variant_adjustments(base, m.job.variant)[1]:
                if note not in self.notes:
                    self.notes.append(f"Changed for the ablation on {m.job.train_preset}: {note}")
        imported = [m for k, m in self.imported_models.items() if k not in self.models]
        if self.train_minutes is not None and (self.models or imported):
            done = "; ".join(
                [
                    f"{m.job.variant} on {m.job.train_preset}: {m.steps_done} steps in "
                    f"{m.train_wall_s / 60.0:.1f} min (stopped by "
                    f"{m.budget_report()['stopped_by']})"
                    for m in self.models.values()
                ]
                + [
                    f"{m.get('variant')} on {m.get('train_dataset')}: {m.get('steps_done')} "
                    f"steps in {float(m.get('train_wall_s', 0.0)) / 60.0:.1f} min (imported "
                    f"from {m['imported_from']['report']})"
                    for m in imported
                ]
            )
            self.notes.append(
                f"Training budget: {self.train_minutes:g} min of training wall time per model "
                f"(evaluation and checkpoint writes excluded), up to {self.train_steps} steps. "
                f"{done}. Steps done depend on the machine's speed and load, so a budgeted "
                "run is not reproducible step for step."
            )
            for note in (step_rate_note(report["models"]), recipe_rate_note(report["models"])):
                if note is not None:
                    self.notes.append(note)
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
