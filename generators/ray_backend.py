"""Ray backend of ``generate``: scenes as tasks on Ray actors, one Blender session each.

Where this sits: :func:`generators.pipeline.generate_dataset` decides *what* to render
(this shard's scenes minus the complete ones, manifest, temp-file clean-up) and calls
:func:`render_scenes` here instead of its local process pool when
``GenerateConfig.backend == "ray"``. Each actor is a worker process that runs the same
task as the local pool, :func:`generators.worker.render_one` (sample -> Cycles ->
atomic write), so the bytes on disk do not depend on the backend, and resume works the
same way (complete scenes are never scheduled; a killed run leaves only temp files,
removed by the next run).

Scheduling: ``workers`` actors, each reserving ``threads`` Ray CPUs (the Cycles
threads), one scene in flight per actor; an actor that finished ``recycle_after``
scenes retires (Blender leaks a little memory per scene) and a fresh one takes its
place. Progress is aggregated on the driver. A lost actor (node failure) is restarted
and its scene re-run, which is safe because a scene's writes are idempotent.

Cluster use: the workers write straight into ``--out``, so it must be a file system that
every node mounts at the same path, and every node needs this package (and bpy)
installed; see ``docs/scaleout.md``. Nothing here imports bpy.
"""

from __future__ import annotations

import os
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from generators.presets import Preset
from generators.spec import RenderSettings

__all__ = ["RayMissingError", "RayPlan", "import_ray", "init_ray", "plan", "render_scenes"]

#: Default Cycles threads per actor when ``--threads`` is not given (ENV.md: one 2-thread
#: Blender process beat two 1-thread ones on 2 cores).
DEFAULT_THREADS = 2


class RayMissingError(ImportError):
    """``ray`` cannot be imported (the ``ray`` extra is not installed)."""


def import_ray() -> Any:
    """Import and return ``ray``, or raise :class:`RayMissingError` with the install hint."""
    try:
        import ray
    except ImportError as e:
        raise RayMissingError(
            "--backend ray needs the ray package, which is not installed; fix: "
            "pip install 'svorf-toolkit[ray]' (or pip install 'ray>=2.9')"
        ) from e
    return ray


def init_ray(ray: Any, address: str | None) -> None:
    """``ray.init`` for the CLIs: join ``address`` (or ``RAY_ADDRESS``), else start a local
    instance whose workers run at the caller's priority.

    Ray starts its worker processes at niceness 15 (``RAY_worker_niceness``), so beside
    other CPU work on the machine (a training, a second protocol) they get a small share
    of the cores and a time-budgeted training makes few steps. Unless the caller set
    ``RAY_worker_niceness`` itself, a local instance started here uses 0. A cluster
    started with ``ray start`` keeps its own setting (docs/scaleout.md).
    """
    os.environ.setdefault("RAY_worker_niceness", "0")
    ray.init(address=address, include_dashboard=False, log_to_driver=False)


@dataclass(frozen=True)
class RayPlan:
    """Actors and CPUs of one Ray generation run.

    Attributes:
        workers: actors (Blender sessions) running at once.
        threads: Cycles threads per actor (= Ray CPUs each actor reserves).
        cluster_cpus: CPUs the Ray cluster reports.
    """

    workers: int
    threads: int
    cluster_cpus: int


def plan(workers: int | None, threads: int | None, cluster_cpus: int, n_scenes: int) -> RayPlan:
    """Actor count and threads for a cluster of ``cluster_cpus`` CPUs.

    Defaults: ``threads`` = 2 (at most the cluster's CPUs), ``workers`` = as many actors
    as the cluster holds, at most one per scene.

    Raises:
        ValueError: the requested actors need more CPUs than the cluster has (their tasks
            would wait forever); the message names the numbers and the fix.
    """
    if cluster_cpus < 1:
        raise ValueError("the Ray cluster reports no CPUs; start workers with `ray start`")
    t = threads if threads is not None else min(DEFAULT_THREADS, cluster_cpus)
    w = workers if workers is not None else max(1, cluster_cpus // t)
    if w * t > cluster_cpus:
        raise ValueError(
            f"--workers {w} x --threads {t} = {w * t} CPUs, but the Ray cluster has "
            f"{cluster_cpus}; lower --workers or --threads"
        )
    return RayPlan(workers=max(1, min(w, n_scenes)), threads=t, cluster_cpus=cluster_cpus)


def _actor_class(ray: Any) -> Any:
    """The Blender worker actor (defined lazily: ``ray`` is an optional dependency)."""

    class BlenderWorker:
        """One worker process holding one Blender session, reused across scenes."""

        def __init__(self, threads: int, out: str) -> None:
            from generators.worker import init_worker

            init_worker(threads)
            # The driver wrote the manifest before starting actors: an actor that cannot
            # see it runs on a node without the shared --out folder.
            if not (Path(out) / "manifest.json").is_file():
                import socket

                raise ValueError(
                    f"--out {out} is not visible on Ray node {socket.gethostname()}: the "
                    f"ray backend writes from every node, so --out must be on a file "
                    f"system shared by all nodes (same path)"
                )

        def render(
            self,
            preset: Preset,
            split: str,
            index: int,
            seed: int,
            render: RenderSettings,
            out: str,
        ) -> dict[str, float]:
            from generators.worker import render_one

            node = ray.get_runtime_context().get_node_id()
            return {
                **render_one(preset, split, index, seed, render, out),
                "pid": os.getpid(),
                "node": node,
            }

        def retire(self) -> None:
            """Close the Blender session and end the process (worker recycling)."""
            from generators.worker import close_worker_session

            close_worker_session()
            ray.actor.exit_actor()

    return ray.remote(max_restarts=2, max_task_retries=2)(BlenderWorker)


def render_scenes(
    preset: Preset,
    split: str,
    indices: Sequence[int],
    seed: int,
    render: RenderSettings,
    out: Path,
    *,
    workers: int | None = None,
    threads: int | None = None,
    recycle_after: int = 40,
    address: str | None = None,
    on_done: Callable[[dict[str, float]], None] | None = None,
) -> tuple[RayPlan, list[dict[str, float]]]:
    """Render and write scenes ``indices`` as Ray actor tasks.

    Uses the running Ray instance if ``ray.init`` was already called in this process;
    otherwise connects to ``address`` (``"auto"``, ``"ray://host:10001"``, ``host:6379``;
    None = the ``RAY_ADDRESS`` environment variable, else a new local instance) and
    shuts down what it started.

    Args:
        preset, split, seed, render: as for :func:`generators.worker.render_one`.
        indices: scene indices to render (the caller removed the complete ones).
        out: the split folder (exists, holds the manifest; shared by all nodes).
        workers, threads: see :func:`plan`.
        recycle_after: scenes per actor before it is replaced.
        address: Ray cluster address.
        on_done: called on the driver with each finished scene's result (progress).

    Returns:
        ``(plan, results)``: the plan used and one ``render_one`` result per scene
        (``index``, ``render_s``, ``scene_s``, ``pid``, and ``node``: the id of the Ray node
        that rendered it), in completion order.

    Raises:
        RayMissingError: ray is not installed.
        ValueError: a plan the cluster cannot run, or ``out`` not visible on a node.
        Any exception a scene raised (the remaining scenes are cancelled).
    """
    ray = import_ray()
    started = False
    if not ray.is_initialized():
        init_ray(ray, address)
        started = True
    try:
        cpus = int(ray.cluster_resources().get("CPU", 0))
        p = plan(workers, threads, cpus, len(indices))
        Worker = _actor_class(ray)
        out_s = str(Path(out).absolute())

        def spawn() -> Any:
            return Worker.options(num_cpus=p.threads).remote(p.threads, out_s)

        queue = deque(indices)
        actors: list[Any] = [spawn() for _ in range(p.workers)]
        done_by = [0] * p.workers
        pending: dict[Any, int] = {}  # ObjectRef -> actor slot
        results: list[dict[str, float]] = []

        def submit(slot: int) -> None:
            i = queue.popleft()
            ref = actors[slot].render.remote(preset, split, i, seed, render, out_s)
            pending[ref] = slot

        try:
            for slot in range(p.workers):
                if queue:
                    submit(slot)
            while pending:
                ready, _ = ray.wait(list(pending), num_returns=1)
                slot = pending.pop(ready[0])
                res = ray.get(ready[0])  # re-raises the scene's exception
                results.append(res)
                if on_done is not None:
                    on_done(res)
                done_by[slot] += 1
                if done_by[slot] >= recycle_after and queue:
                    actors[slot].retire.remote()
                    actors[slot], done_by[slot] = spawn(), 0
                if queue:
                    submit(slot)
            # Orderly end: each actor closes its Blender session (temp folder) and exits.
            ray.wait([a.retire.remote() for a in actors], num_returns=len(actors), timeout=60)
        finally:
            for a in actors:  # after an error: stop the other scenes now
                ray.kill(a, no_restart=True)
        return p, results
    finally:
        if started:
            ray.shutdown()
