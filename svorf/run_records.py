"""What a training run records besides its checkpoint, and its clock.

:class:`TrainSummary` (``summary.json``), :class:`TrainingDiverged` (what the NaN guards
raise), the ``log.jsonl`` / ``eval.jsonl`` helpers, the process's peak memory and
:class:`Budget`, the training wall time of a time-budgeted run, with :class:`RateCheck`, its
early word on a machine slower than its recipe's. The loop that uses them is
``svorf.train``, which re-exports the two public classes.
"""

from __future__ import annotations

import contextlib
import json
import resource
import sys
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
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


def log_step(
    path: Path,
    done: int,
    wall: float,
    lr: float,
    loss: float,
    parts: dict[str, Any],
    gnorm: Any,
    steps_per_s: float,
) -> None:
    """Append step ``done``'s line to the run's ``log.jsonl`` at ``path``."""
    append_jsonl(
        path,
        {
            "step": done,
            "wall_s": round(wall, 3),
            "lr": lr,
            "loss": loss,
            "parts": {k: float(v) for k, v in parts.items()},
            "steps_per_s": round(steps_per_s, 4),
            "grad_norm": float(gnorm),
        },
    )


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


@dataclass
class RateCheck:
    """A time-budgeted run's early check of its speed against its recipe's.

    Under a minute budget the machine decides how many steps a run makes, and fewer steps
    score lower. ``svorf.train`` measures a call's steps per minute once, over the second
    half of its first ``after_s`` seconds of training (:meth:`speak`), and prints
    :meth:`note` when the speed is under ``below`` x the slowest speed the recipe was
    measured at, so the user learns it at once instead of from a weaker result at the end.

    Attributes:
        recipe: the recipe's name ("cpu recipe").
        expected: steps per minute at which its minute budgets were measured (slowest,
            fastest; ``svorf.registry.Recipe.steps_per_minute``).
        max_wall_s: the run's training-time budget in seconds.
        float32_here: whether the recipe's bf16 autocast (``"auto"``) resolves to float32
            on this device, as on a CPU without native bf16.
        after_s: seconds of the call's training after which the speed is known.
        below: the fraction of the slowest expected speed under which it speaks.
    """

    recipe: str
    expected: tuple[float, float]
    max_wall_s: float
    float32_here: bool = False
    after_s: float = 180.0
    below: float = 0.8
    _mark: tuple[int, float] | None = field(default=None, init=False, repr=False)
    """(step, wall time) at half of ``after_s``, where the measured window starts."""

    @staticmethod
    def probe_seconds(max_wall_s: float) -> float:
        """When to measure: 5% of the budget, within 1 to 5 minutes."""
        return min(300.0, max(60.0, 0.05 * max_wall_s))

    def speak(
        self, done: int, wall: float, wall_offset: float, limit: int, bar: Any = None
    ) -> bool:
        """At step ``done`` and training wall time ``wall`` (this call started at wall time
        ``wall_offset``; step limit ``limit``): False before ``after_s`` seconds of the
        call's training; after them True, having printed :meth:`note` on stderr (above the
        progress bar ``bar``) where it has one and the budget, not the step limit, will end
        the run. The speed is that of the window's second half, past the first steps. A
        run's first minutes are its fastest (a 5-minute cpu-recipe run made 325 steps in
        its first minute and 245-290 in each later one), so the projection is on the high
        side and the comparison with the recipe's whole-run speeds errs towards silence."""
        call_s = wall - wall_offset
        if self._mark is None:
            if call_s >= self.after_s / 2.0:
                self._mark = (done, wall)
            return False
        if call_s < self.after_s:
            return False
        steps, secs = done - self._mark[0], wall - self._mark[1]
        if steps <= 0 or secs <= 0:
            return True
        rate = steps / secs * 60.0
        projected = done + int(rate / 60.0 * max(self.max_wall_s - wall, 0.0))
        if projected >= limit:  # the step limit, not the budget, ends this run
            return True
        note = self.note(rate, projected)
        if note is not None:
            msg = f"svorf train: {note}"
            if bar is not None:
                bar.write(msg, file=sys.stderr)
            else:
                print(msg, file=sys.stderr, flush=True)
        return True

    def note(self, steps_per_minute: float, projected: int) -> str | None:
        """The warning for a run training at ``steps_per_minute`` that will have made about
        ``projected`` steps at the end of its budget; None at or above ``below`` x the
        slowest expected speed."""
        lo, hi = self.expected
        if steps_per_minute >= self.below * lo:
            return None
        minutes = self.max_wall_s / 60.0
        recipe_steps = int(round((lo + hi) / 2.0 * minutes, -2))
        here = (
            " on CPUs with native bf16; this one has none, so it trains in float32"
            if self.float32_here
            else ""
        )
        return (
            f"{steps_per_minute:.0f} steps per minute here: at this speed this {minutes:.3g}-minute "
            f"budget makes about {projected:,} steps. The {self.recipe}'s results were measured at "
            f"{lo:.0f}-{hi:.0f} steps per minute (about {recipe_steps:,} steps in "
            f"{minutes:.3g} minutes){here}. Fewer steps score lower: for the recipe's step "
            f"count, give --steps {recipe_steps} instead of the minute budget (about "
            f"{recipe_steps / steps_per_minute:.0f} minutes here)."
        )


def recipe_rate_check(
    model_cfg: Any, train_cfg: Any, device: Any, max_wall_s: float | None, main: bool = True
) -> RateCheck | None:
    """The early speed check of a time-budgeted run of a recipe's model; None without a
    budget, off the main process, or for a model whose speed was not measured (not a
    recipe's, or a variant of one: ``svorf.train_config.recipe_of``)."""
    from svorf.config import bf16_autocast_on
    from svorf.train_config import recipe_of

    if max_wall_s is None or not main:
        return None
    recipe = recipe_of(model_cfg, train_cfg)
    if recipe is None or recipe.steps_per_minute is None:
        return None
    return RateCheck(
        recipe.name,
        recipe.steps_per_minute,
        max_wall_s,
        float32_here=model_cfg.bf16_autocast == "auto" and not bf16_autocast_on("auto", device),
        after_s=RateCheck.probe_seconds(max_wall_s),
    )
