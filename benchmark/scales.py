"""Benchmark scales: dataset sizes, resolution, render quality and evaluation size.

Where this sits: every protocol reads one :class:`ScaleSettings` (``--scale``).
Model sizes and training steps per scale belong to ``svorf``
(``svorf.config.model_config(scale)`` / ``svorf.train.train_config(scale, preset)``;
at the ``cpu`` scale the CLEVR-567 family uses ``svorf.recipe.recipe_configs``, see
``benchmark.adapter.base_configs``); this module only fixes what the benchmark itself decides, and the report copies
both into ``scale_settings`` so every number is written down.

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

__all__ = ["SCALES", "ScaleSettings", "get_scale"]


@dataclass(frozen=True)
class ScaleSettings:
    """What one benchmark scale means.

    Attributes:
        name: ``smoke`` / ``cpu`` / ``paper``.
        resolution: rendered image side (pixels) of every dataset.
        train_scenes: training scenes per preset (``default`` for presets not listed).
        test_scenes: test scenes per preset.
        render_samples: Cycles samples per pixel (None = the generator's default).
        denoise: OpenImageDenoise after rendering (None = the generator's default).
        eval_scenes: test scenes evaluated (None = all).
        train_steps: training steps (None = ``svorf.train.train_config(scale)``'s).
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
        resolution=32,
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
        resolution=64,
        train_scenes={"default": 240, "room-diverse": 400},
        test_scenes={"default": 50},
        render_samples=16,
        denoise=True,
        eval_scenes=None,
        speed_steps=20,
        speed_warmup=3,
        notes=(
            (
                "cpu: 64x64 renders, 240 training scenes (400 for Room-Diverse), 50 test "
                "scenes, the svorf 'cpu' model; CLEVR-567-family models train with the cpu "
                "recipe (svorf.recipe.recipe_configs, docs/notes/cpu_recipe.md), Room models with "
                "svorf's cpu schedule (a 2-core machine, hours per protocol)."
            ),
        ),
    ),
    "paper": ScaleSettings(
        name="paper",
        resolution=256,
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


def get_scale(name: str) -> ScaleSettings:
    """The settings of scale ``name``; a one-line ValueError naming the known scales
    otherwise ("did you mean ...?" for a near miss)."""
    return SCALES[choose(name, SCALES, "scale")]
