"""What the ``speed`` protocol measures at each scale: :class:`SpeedOptions`.

Where this sits: :func:`benchmark.protocols.speed.run_speed` takes a :class:`SpeedOptions`
(:func:`default_options` of the scale unless given, from
``benchmark.scales.SPEED_DEFAULTS``) and hands it to the measurements of :mod:`.compare` and
:mod:`.generator`.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any

from benchmark.scales import SPEED_DEFAULTS

__all__ = ["SpeedOptions", "default_options"]


@dataclass(frozen=True)
class SpeedOptions:
    """What the ``speed`` protocol measures beyond the scale's ``speed_steps``/``speed_warmup``.

    Attributes:
        compare_batches: scenes per step of the sVORF / uORF-style comparisons, one
            comparison each (1 = Table 8's setting; None = the scale's training batch;
            a batch that repeats after resolving is measured once).
        compare_steps: timed steps per comparison run (None = ``speed_steps``).
        compare_warmup: untimed warm-up steps per comparison run (None = ``speed_warmup``).
        compare_repeats: fresh-subprocess runs of each configuration, alternating.
        memory_fraction: each worker's address-space limit as a fraction of the memory
            available when the protocol starts (a configuration that does not fit fails
            with a null row instead of pushing other processes out of memory).
        render_repeats: test scenes timed for the inference rows (median).
        generator: measure the generator; None = when ``data_source`` is ``generator``
            and ``bpy`` is importable.
        gen_scenes, gen_resolution, gen_samples: the generator measurement's split
            (``clevr567`` train scenes, pixels, Cycles samples per pixel).
        gen_workers: worker counts of the generator scaling rows (the first is the
            reference of ``scaling_speedup`` and of ``overhead_ratio``).
        baseline_scenes, baseline_resolution, baseline_samples, baseline_ref_samples,
            baseline_psnr_scenes: ``generate`` against the straightforward bpy script
            (:func:`benchmark.tools.bench_baseline.compare`): scenes each side renders,
            pixels, Cycles samples of both sides (None = the shipped default), samples
            of the no-denoiser reference, scenes compared with it.
        baseline_denoisers: one comparison per entry of
            :data:`benchmark.tools.bench_baseline.BASELINE_DENOISERS` (``factory``: the
            script keeps Blender's denoiser defaults; ``tuned``: it borrows
            ``generate``'s); empty = no comparison.
    """

    compare_batches: tuple[int | None, ...] = (1, None)
    compare_steps: int | None = None
    compare_warmup: int | None = None
    compare_repeats: int = 3
    memory_fraction: float = 0.6
    render_repeats: int = 3
    generator: bool | None = None
    gen_scenes: int = 8
    gen_resolution: int = 32
    gen_samples: int = 4
    gen_workers: tuple[int, ...] = (1, 2)
    baseline_scenes: int = 20
    baseline_resolution: int = 128
    baseline_samples: int | None = None
    baseline_ref_samples: int = 512
    baseline_psnr_scenes: int = 2
    baseline_denoisers: tuple[str, ...] = ("factory", "tuned")

    def __post_init__(self) -> None:
        for name in ("compare_repeats", "render_repeats", "gen_scenes", "gen_resolution",
                     "baseline_scenes", "baseline_ref_samples", "baseline_psnr_scenes"):  # fmt: skip
            if int(getattr(self, name)) < 1:
                raise ValueError(f"SpeedOptions.{name} must be >= 1, got {getattr(self, name)}")
        if not self.compare_batches:
            raise ValueError("SpeedOptions.compare_batches must name at least one batch")
        for b in self.compare_batches:
            if b is not None and int(b) < 1:
                raise ValueError(f"SpeedOptions.compare_batches must be >= 1 each, got {b}")
        for name in ("compare_steps", "compare_warmup", "gen_samples", "baseline_samples"):
            v = getattr(self, name)
            if v is not None and int(v) < (0 if name == "compare_warmup" else 1):
                raise ValueError(f"SpeedOptions.{name} must be a positive count, got {v}")
        if not 0.0 < self.memory_fraction <= 1.0:
            raise ValueError(
                f"SpeedOptions.memory_fraction must be in (0, 1], got {self.memory_fraction}"
            )
        if not self.gen_workers or min(self.gen_workers) < 1:
            raise ValueError(f"SpeedOptions.gen_workers must be >= 1 each, got {self.gen_workers}")
        if self.baseline_psnr_scenes > self.baseline_scenes:
            raise ValueError(
                f"SpeedOptions.baseline_psnr_scenes ({self.baseline_psnr_scenes}) must be <= "
                f"baseline_scenes ({self.baseline_scenes})"
            )
        from benchmark.tools.bench_baseline import BASELINE_DENOISERS  # no bpy import

        bad = [d for d in self.baseline_denoisers if d not in BASELINE_DENOISERS]
        if bad:
            raise ValueError(
                f"SpeedOptions.baseline_denoisers: unknown {bad}; use any of {BASELINE_DENOISERS}"
            )

    def to_dict(self) -> dict[str, Any]:
        d = dataclasses.asdict(self)
        d["gen_workers"] = list(self.gen_workers)
        d["compare_batches"] = list(self.compare_batches)
        d["baseline_denoisers"] = list(self.baseline_denoisers)
        return d


def default_options(scale: str) -> SpeedOptions:
    """Per-scale defaults (``benchmark.scales.SPEED_DEFAULTS``): smoke is quick (1 repeat,
    2 generator scenes at 1 sample)."""
    return SpeedOptions(**SPEED_DEFAULTS.get(scale, {}))
