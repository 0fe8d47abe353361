"""What a training run records besides its checkpoint, and its clock.

:class:`TrainSummary` (``summary.json``), :class:`TrainingDiverged` (what the NaN guards
raise), the ``log.jsonl`` / ``eval.jsonl`` helpers, the process's peak memory and
:class:`Budget`, the training wall time of a time-budgeted run. The loop that uses them is
``svorf.train``, which re-exports the two public classes.
"""

from __future__ import annotations

import contextlib
import json
import resource
import sys
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from scenefmt import atomic_write_bytes


class TrainingDiverged(RuntimeError):
    """The loss or a gradient became NaN/Inf; the last good checkpoint is left untouched.

    Attributes:
        step: the optimizer step (1-based, as in ``log.jsonl``) whose loss or gradient was
            not finite.
    """

    def __init__(self, message: str, step: int) -> None:
        super().__init__(message)
        self.step = int(step)

    def __reduce__(self) -> tuple[Any, ...]:  # picklable across processes (Ray, torchrun)
        return (type(self), (str(self), self.step))


@dataclass(frozen=True)
class TrainSummary:
    """What :func:`train` returns; :meth:`to_dict` is ``summary.json``.

    Attributes:
        steps: optimizer steps the run has finished (the checkpoint's step).
        start_step: the step this call started from (0, or the resumed checkpoint's).
        final_loss: the last step's loss (NaN before any step).
        wall_s: seconds of this call.
        train_wall_s: training seconds of all calls (evaluation and checkpointing excluded).
        s_per_step: training seconds per step of this call (NaN: no step run).
        peak_rss_mb: peak resident memory of the process in MiB.
        params: the model's parameter count.
        device: the torch device trained on.
        bf16_autocast_active: what ``bf16_autocast`` resolved to on this device.
        checkpoint / log: paths of ``checkpoint.pt`` and ``log.jsonl``.
        dataset_fingerprint: the training split's fingerprint.
        init_from: what started the run's weights (:func:`init_weights_from`), or None.
        world_size: ranks under torchrun, None in a single process (not in the JSON).
    """

    steps: int
    start_step: int
    final_loss: float
    wall_s: float
    train_wall_s: float
    s_per_step: float
    peak_rss_mb: float
    params: int
    device: str
    bf16_autocast_active: bool
    checkpoint: str
    log: str
    dataset_fingerprint: str
    init_from: dict[str, Any] | None = None
    world_size: int | None = None

    def to_dict(self) -> dict[str, Any]:
        """The summary as ``summary.json`` holds it."""
        d = {k: getattr(self, k) for k in self.__dataclass_fields__ if k != "world_size"}
        if self.world_size is not None:
            d["world_size"] = self.world_size
        return d


# --------------------------------------------------------------------------- run folder


def truncate_jsonl(path: Path, max_step: int) -> None:
    """Drop lines logged after the checkpoint (a crash may have logged past it)."""
    if not path.is_file():
        return
    keep = []
    for line in path.read_text().splitlines():
        try:
            if json.loads(line)["step"] <= max_step:
                keep.append(line)
        except (ValueError, KeyError, TypeError):
            continue  # a torn last line
    atomic_write_bytes(path, "".join(x + "\n" for x in keep).encode())


def append_jsonl(path: Path, row: dict[str, Any]) -> None:
    """Append one JSON line (keys sorted) to ``log.jsonl`` or ``eval.jsonl``."""
    with open(path, "a") as f:
        f.write(json.dumps(row, sort_keys=True) + "\n")


def peak_rss_mb() -> float:
    """Peak resident memory of this process in MiB (``TrainSummary.peak_rss_mb``)."""
    # ru_maxrss is KiB on Linux, bytes on macOS.
    r = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return r / (1024.0 * 1024.0) if sys.platform == "darwin" else r / 1024.0


class Budget:
    """The run's training wall time: time since the loop started, less the pauses
    (evaluation, checkpoint writing), plus the earlier calls' time; and the budget
    ``max_wall_s`` of a time-budgeted run (None = steps only)."""

    def __init__(self, wall_offset: float, max_wall_s: float | None) -> None:
        self.t0 = time.perf_counter()
        self.paused = 0.0
        self.wall_offset = wall_offset
        self.max_wall_s = max_wall_s

    def wall(self, now: float) -> float:
        """Training wall time at ``now`` (a ``time.perf_counter()`` value)."""
        return self.wall_offset + now - self.t0 - self.paused

    def progress(self, step: int, steps: int) -> float:
        """How far the run is, for the learning-rate schedule: ``step / steps``, or the
        wall-time fraction of the budget when that is larger."""
        progress = step / steps
        if self.max_wall_s is not None:
            now_wall = self.wall(time.perf_counter())
            progress = max(progress, now_wall / self.max_wall_s if self.max_wall_s > 0 else 1.0)
        return progress

    def spent(self, wall: float) -> bool:
        """Whether the budget is used up at training wall time ``wall``."""
        return self.max_wall_s is not None and wall >= self.max_wall_s

    @contextlib.contextmanager
    def paused_while(self) -> Iterator[None]:
        """Time spent inside is not training time."""
        tp = time.perf_counter()
        yield
        self.paused += time.perf_counter() - tp
