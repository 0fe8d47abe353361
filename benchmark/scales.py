"""Benchmark scales: dataset sizes, render quality, evaluation size and how hard the
timing protocols measure.

Where this sits: every protocol reads one :class:`ScaleSettings` (``--scale``). What a
scale means for the model, its training and the cpu recipe is svorf's registry
(``svorf.registry.SCALES``, reached through ``benchmark.adapter.base_configs``, the same
configs ``svorf train --scale S`` uses); the scale names and the image resolution come from
there too. This module only fixes what the benchmark itself decides: dataset sizes and
render quality (:data:`SCALES`), the ``speed`` protocol's defaults
(:data:`SPEED_DEFAULTS`) and the ``tradeoff`` protocol's repeats and sizes
(:data:`TRADEOFF`). The report copies the settings into ``scale_settings`` so every number
is written down.

- ``smoke``: CI and tests; tiny datasets (4 train / 2 test scenes at 32x32, one
  render sample), a few training steps. Minutes for a protocol on 2 cores. It
  checks the plumbing; its metrics mean nothing.
- ``cpu``: the honest small-machine version for a 2-core CPU (hours per protocol):
  64x64, a few hundred training scenes, the cpu recipe for CLEVR-567 models; see the
  report for whether it decomposes. ``--datasets clevr567 --train-minutes 60`` makes one
  table fit in about an hour and a half.
- ``paper``: the paper's dataset sizes (uORF splits: 1000/500, Room-Diverse 5000/500)
  at 256x256 and the paper's model; meant for a GPU.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any

from scenefmt.cli_util import choose
from svorf.registry import SCALE_NAMES
from svorf.registry import SCALES as SVORF_SCALES

__all__ = [
    "SCALES",
    "SPEED_DEFAULTS",
    "TRADEOFF",
    "ScaleSettings",
    "TradeoffSettings",
    "get_scale",
]


@dataclass(frozen=True)
class ScaleSettings:
    """What one benchmark scale means.

    Attributes:
        name: ``smoke`` / ``cpu`` / ``paper``.
        resolution: rendered image side (pixels) of every dataset: the image size of the
            scale's model (``svorf.registry.SCALES[name].image_size``).
        train_scenes: training scenes per preset (``default`` for presets not listed).
        test_scenes: test scenes per preset.
        render_samples: Cycles samples per pixel (None = the generator's default).
        denoise: OpenImageDenoise after rendering (None = the generator's default).
        eval_scenes: test scenes evaluated (None = all).
        train_steps: training steps (None = the svorf scale's, ``svorf.registry``).
        speed_steps: timed training steps of the ``speed`` protocol (after warm-up).
        speed_warmup: untimed warm-up steps of the ``speed`` protocol.
        decompose_threshold: FG-ARI (percent) a model must reach, and exceed both the best
            chance baseline and its own scene-shuffle control (``fg_ari_shuffled``) by
            ``decompose_margin``, to be said to decompose.
    """

    name: str
    resolution: int
    train_scenes: dict[str, int]
    test_scenes: dict[str, int]
    render_samples: int | None = None
    denoise: bool | None = None
    eval_scenes: int | None = None
    train_steps: int | None = None
    speed_steps: int = 5
    speed_warmup: int = 1
    decompose_threshold: float = 50.0
    decompose_margin: float = 20.0
    notes: tuple[str, ...] = field(default_factory=tuple)

    def n_scenes(self, preset: str, split: str) -> int:
        """Scene count of ``preset``/``split`` at this scale."""
        table = self.train_scenes if split == "train" else self.test_scenes
        return int(table.get(preset, table["default"]))

    def to_dict(self) -> dict[str, Any]:
        d = dataclasses.asdict(self)
        d["notes"] = list(self.notes)
        return d


SCALES: dict[str, ScaleSettings] = {
    "smoke": ScaleSettings(
        name="smoke",
        resolution=SVORF_SCALES["smoke"].image_size,
        train_scenes={"default": 4},
        test_scenes={"default": 2},
        render_samples=1,
        denoise=False,
        # A few steps of svorf's smoke train config (its default is 30); 10 keeps the
        # 8-model ablation within minutes on 2 shared cores.
        train_steps=10,
        speed_steps=3,
        speed_warmup=1,
        notes=(
            (
                "smoke checks the plumbing only: a few training steps on 4 scenes cannot "
                "decompose a scene, so its metrics are at chance level by design."
            ),
            (
                "smoke renders its ground truth with 1 Cycles sample per pixel and no "
                "denoiser (32x32), so the ground-truth images look speckled: that is the "
                "renderer's noise at 1 sample, not a broken dataset."
            ),
        ),
    ),
    "cpu": ScaleSettings(
        name="cpu",
        resolution=SVORF_SCALES["cpu"].image_size,
        # CLEVR-567 and its held-out-appearance twin train on 1,000 scenes, as in the paper:
        # with 240 the cpu recipe was data-limited (60-minute runs, seeds 0 / 1: FG-ARI 69.6 /
        # 70.2 with 1,000 scenes against 63.0-68.1 in six runs with 240; docs/notes/cpu_recipe.md).
        train_scenes={
            "default": 240,
            "clevr567": 1000,
            "clevr567-heldout": 1000,
            "room-diverse": 400,
        },
        test_scenes={"default": 50},
        render_samples=16,
        denoise=True,
        eval_scenes=None,
        speed_steps=20,
        speed_warmup=3,
        notes=(
            (
                "cpu: 64x64 renders, 1,000 training scenes for CLEVR-567 and its held-out-appearance "
                "twin (240 for the other presets, 400 for Room-Diverse), 50 test "
                "scenes, the svorf 'cpu' model; CLEVR-567-family and Room-Chair models train with "
                "the cpu recipe (svorf.registry, docs/notes/cpu_recipe.md; Room-Chair with 6 "
                "slots, the paper's 5 and a spare), Room-Diverse models "
                "with svorf's cpu schedule (a 2-core machine, hours per protocol)."
            ),
        ),
    ),
    "paper": ScaleSettings(
        name="paper",
        resolution=SVORF_SCALES["paper"].image_size,
        train_scenes={"default": 1000, "room-diverse": 5000},
        test_scenes={"default": 500},
        render_samples=None,
        denoise=None,
        speed_steps=50,
        speed_warmup=5,
        notes=(
            (
                "paper: the uORF split sizes (1000/500, Room-Diverse 5000/500) rendered at "
                "256x256 (the paper's encoder input; svorf.data only down-samples) and the "
                "paper's model and schedule; needs a GPU."
            ),
        ),
    ),
}


assert tuple(SCALES) == SCALE_NAMES  # internal invariant: svorf's scales, in its order


#: Per-scale defaults of the ``speed`` protocol: ``SpeedOptions`` fields that differ from
#: its defaults (``benchmark.protocols.speed.options.default_options``). smoke is quick
#: (1 repeat, 2 generator scenes at 1 sample); paper renders its generator scenes larger.
SPEED_DEFAULTS: dict[str, dict[str, Any]] = {
    "smoke": {
        "compare_repeats": 1,
        "render_repeats": 1,
        "gen_scenes": 2,
        "gen_samples": 1,
        "baseline_scenes": 1,
        "baseline_resolution": 32,
        "baseline_samples": 1,
        "baseline_ref_samples": 16,
        "baseline_psnr_scenes": 1,
        "baseline_denoisers": ("factory",),
    },
    "cpu": {},
    "paper": {"gen_scenes": 16, "gen_resolution": 128, "gen_samples": 64},
}


@dataclass(frozen=True)
class TradeoffSettings:
    """How hard the ``tradeoff`` protocol measures at one scale.

    Attributes:
        repeats: timed interleaved repeats (the median is taken over them).
        warmup: untimed repeats before (allocator, caches).
        threads: torch intra-op threads during the run (None = leave as is).
        sharp: add the ``sharp-m`` weight set.
        render_scenes: test scenes each point of the render curve renders (every view).
        render_repeats: timed interleaved repeats of the render curve.
        generator_scenes: clevr567 test scenes of the generator curve (every view).
        generator_ref_samples: samples per pixel of its reference render.
        generator: measure the generator curve (needs bpy).
    """

    repeats: int
    warmup: int
    threads: int | None
    sharp: bool = True
    render_scenes: int = 2
    render_repeats: int = 1
    generator_scenes: int = 1
    generator_ref_samples: int = 64
    generator: bool = True


#: The ``tradeoff`` protocol's settings per scale.
TRADEOFF: dict[str, TradeoffSettings] = {
    # Tiny model, 2 scenes x 64 rays: seconds; one thread so tests stay quiet on 2 cores.
    "smoke": TradeoffSettings(repeats=3, warmup=1, threads=1),
    # The cpu-scale model and batch (4 x 128 rays) on a 2-core machine: minutes; the render
    # curve renders 4 test scenes x 4 views at 64x64 per point (~0.3-0.6 s per view).
    # The generator curve: 2 scenes x 4 views at 64x64 against a 512-sample reference.
    "cpu": TradeoffSettings(
        repeats=7,
        warmup=2,
        threads=2,
        render_scenes=4,
        render_repeats=2,
        generator_scenes=2,
        generator_ref_samples=512,
    ),
    # The paper's model and batch (16 x 64 rays); meant for a GPU.
    "paper": TradeoffSettings(
        repeats=5,
        warmup=2,
        threads=None,
        render_scenes=8,
        render_repeats=2,
        generator_scenes=4,
        generator_ref_samples=512,
    ),
}


def get_scale(name: str) -> ScaleSettings:
    """The settings of scale ``name``; a one-line ValueError naming the known scales
    otherwise ("did you mean ...?" for a near miss)."""
    return SCALES[choose(name, SCALES, "scale")]
