"""``benchmark run ... --backend ray``: a table protocol's jobs as Ray tasks.

Where this sits: :func:`benchmark.runner.run_table_protocol` calls
:func:`run_jobs_on_ray` before its row loop when ``Context.backend == "ray"``. This
module schedules the protocol's three kinds of job, each identified by the cache key
the local path already uses:

1. datasets: every train/test split the rows need, generated on the driver with the
   generator's Ray backend (``generators.ray_backend``: scenes as tasks on Blender
   actors across the cluster);
2. training runs: one Ray task per distinct model key (``<out>/runs/<key>/``) that has
   no finished marker, all submitted at once (:func:`benchmark.jobs.train_run`);
3. evaluations: one Ray task per (model key, test fingerprint) without a cached result
   (:func:`benchmark.jobs.evaluate_run`).

The row loop that follows then finds every model and evaluation in the caches and only
assembles rows, baselines, figures and the report, exactly as a local run would. Resume
is the local one: a finished job is never scheduled again, and an interrupted training
task resumes from its checkpoint when the protocol is run again.

Cluster use: tasks read and write ``--data`` and ``--out`` directly, so both must be on
a file system every node mounts at the same path, and every node needs this package
installed (see ``docs/scaleout.md``).
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

from benchmark.datasets import DatasetInfo
from benchmark.generator_bridge import DatasetUnavailable
from benchmark.jobs import read_eval
from benchmark.log import log
from scenefmt.cli_util import progress_kwargs

__all__ = ["RayJobError", "cpus_per_task", "run_jobs_on_ray"]


class RayJobError(RuntimeError):
    """A training or evaluation task failed on a Ray worker (one line naming the job)."""


def cpus_per_task(cluster_cpus: int, n_tasks: int) -> int:
    """Ray CPUs (= torch threads) each of ``n_tasks`` concurrent tasks reserves.

    The cluster's CPUs shared evenly, at least 1: 2 CPUs and 3 models -> 1 CPU each
    (two run at once, the third waits); 16 CPUs and 3 models -> 5 each.
    """
    if n_tasks < 1:
        return 1
    return max(1, int(cluster_cpus) // int(n_tasks))


def _train_task(threads: int, kwargs: dict[str, Any]) -> dict[str, Any]:
    import torch

    from benchmark.jobs import train_run

    torch.set_num_threads(threads)
    payload, _ = train_run(**kwargs)
    return payload


def _eval_task(threads: int, args: tuple, kwargs: dict[str, Any]) -> str:
    import torch

    from benchmark.jobs import evaluate_run

    torch.set_num_threads(threads)
    evaluate_run(*args, **kwargs)
    return str(args[2])


def _gather(ray: Any, refs: dict[Any, str], what: str, progress: bool) -> None:
    """Wait for every task; re-raise the first failure with the job it belongs to."""
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=len(refs), desc=f"ray {what}", dynamic_ncols=True, **progress_kwargs())
    pending = dict(refs)
    try:
        while pending:
            ready, _ = ray.wait(list(pending), num_returns=1)
            name = pending.pop(ready[0])
            try:
                ray.get(ready[0])
            except Exception as err:  # a task's own exception, wrapped by Ray
                for r in pending:
                    ray.cancel(r, force=True)
                cause = getattr(err, "cause", None) or err
                raise RayJobError(
                    f"Ray {what} job {name} failed: {type(cause).__name__}: {cause}"
                ) from err
            if bar is not None:
                bar.update(1)
    finally:
        if bar is not None:
            bar.close()


def run_jobs_on_ray(ctx: Any, measured: list[Any]) -> dict[str, int]:
    """Generate, train and evaluate everything ``measured`` needs as Ray tasks.

    Args:
        ctx: the protocol's :class:`benchmark.context.Context` (``backend == "ray"``).
        measured: the protocol's measured rows (after ``--datasets``).

    Returns:
        Counts of the jobs run: ``{"train": n, "eval": m, "cluster_cpus": c}``.

    Raises:
        generators.ray_backend.RayMissingError: ray is not installed.
        RayJobError: a training or evaluation task failed (names the job).
    """
    from generators.ray_backend import import_ray, init_ray

    ray = import_ray()
    started = not ray.is_initialized()
    if started:
        init_ray(ray, ctx.address)
    try:
        res = ray.cluster_resources()
        cpus = int(res.get("CPU", 1))
        use_gpu = str(ctx.device).startswith("cuda")
        if use_gpu and res.get("GPU", 0) < 1:
            raise ValueError(
                f"--device {ctx.device} with --backend ray needs GPUs in the Ray cluster, "
                "which reports none; start the workers with GPUs or use --device cpu"
            )
        # 1. datasets (the scenes themselves render on Ray actors, see Context.dataset).
        tests: dict[str, DatasetInfo] = {}
        for spec in measured:
            try:
                tests[spec.dataset] = ctx.dataset(spec.dataset, "test")
                if ctx.may_train(spec.job) or not ctx.no_cached_run(spec.job):
                    ctx.train_dataset(spec.job)
            except DatasetUnavailable:
                tests.pop(spec.dataset, None)  # the row loop records why
        specs = [s for s in measured if s.dataset in tests]

        # 2. training runs: one task per model key without a finished marker.
        jobs: dict[str, Any] = {}
        for spec in specs:
            # A model that starts from another's weights trains after it, in the row loop.
            if (
                ctx.may_train(spec.job)
                and ctx.init_job(spec.job) is None
                and ctx.model(spec.job, train=False) is None
            ):
                jobs.setdefault(ctx.model_key(spec.job)[0], spec.job)
        t = time.perf_counter()
        if jobs:
            threads = cpus_per_task(cpus, len(jobs))
            log(
                f"ray: {len(jobs)} training run(s) on a cluster of {cpus} CPUs, "
                f"{threads} CPU(s) each"
            )
            task = ray.remote(_train_task)
            refs = {}
            for key, job in jobs.items():
                ds = ctx.train_dataset(job)
                mcfg, tcfg = ctx.configs(job)
                kwargs = {
                    "ds_path": ds.path,
                    "run_dir": ctx.out / "runs" / key,
                    "mcfg": mcfg,
                    "tcfg": tcfg,
                    "key": key,
                    "key_src": ctx.model_key(job)[1],
                    "job": job,
                    "progress": False,
                    "max_wall_s": ctx.train_budget_s,
                }
                opts = {"num_cpus": threads, "num_gpus": 1 if use_gpu else 0}
                refs[task.options(**opts).remote(threads, kwargs)] = (
                    f"{job.variant} on {job.train_preset} (run {key})"
                )
            _gather(ray, refs, "training", ctx.progress)
            ctx.trained_elsewhere.update(jobs)
        ctx.timers["training"] += time.perf_counter() - t

        # 3. evaluations: one task per (model, test set) without a cached result.
        evals: dict[Path, tuple] = {}
        for spec in specs:
            rec = ctx.model(spec.job, train=False)
            test = tests[spec.dataset]
            d = ctx.eval_dir(rec, test)
            if d not in evals and read_eval(d) is None:
                evals[d] = (rec, test)
        t = time.perf_counter()
        if evals:
            threads = cpus_per_task(cpus, len(evals))
            log(f"ray: {len(evals)} evaluation(s), {threads} CPU(s) each")
            task = ray.remote(_eval_task)
            refs = {}
            for d, (rec, test) in evals.items():
                kwargs = {
                    "image_size": rec.model_config.get("image_size"),
                    "device": ctx.device,
                    "max_scenes": ctx.settings.eval_scenes,
                    "lpips_weights": ctx.lpips_weights,
                    "progress": False,
                    "refine_steps": ctx.refine_slots,
                    "refine_lr": ctx.refine_lr,
                }
                opts = {"num_cpus": threads, "num_gpus": 1 if use_gpu else 0}
                refs[task.options(**opts).remote(threads, (rec.run_dir, test, d), kwargs)] = (
                    f"{rec.job.variant} on {test.name} (run {rec.key})"
                )
            _gather(ray, refs, "evaluation", ctx.progress)
        ctx.timers["evaluation"] += time.perf_counter() - t
        ctx.notes.append(
            f"Backend ray: {len(jobs)} training run(s) and {len(evals)} evaluation(s) ran as "
            f"Ray tasks on a cluster of {cpus} CPUs"
            + (f" at {ctx.address}" if ctx.address else "")
            + "; finished jobs found in the caches were not scheduled."
        )
        return {"train": len(jobs), "eval": len(evals), "cluster_cpus": cpus}
    finally:
        if started:
            ray.shutdown()
