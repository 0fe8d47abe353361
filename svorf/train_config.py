"""Training configs: ``TrainConfig``, the configs of a scale and preset, and the config key.

Where this sits: below ``svorf.train`` (the loop) and ``svorf.checkpoint`` (which saves
these configs as JSON dicts in every checkpoint); beside ``svorf.config``, which does the
same for the model (``ModelConfig``, ``model_config``). :func:`run_configs` is the one place
that decides the (model, train) configs of a scale and preset: ``svorf train``,
``benchmark.tools.recipe`` and the benchmark's ``--scale`` all go through it, and
:func:`config_key` names what a run learns (``svorf config`` prints it). What each scale,
preset and recipe sets is data in ``svorf.registry``; the names :data:`PRESETS`,
:data:`SCALES`, :data:`CPU_RECIPE` ... here are views of it. The learning-rate schedule
(:func:`lr_at`) and the device choice (:func:`resolve_device`) live here too. Everything is
re-exported by ``svorf.train``, the old home of these names.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
from dataclasses import dataclass
from typing import Any

import torch

from scenefmt.cli_util import choose
from svorf import registry
from svorf.config import ModelConfig, model_config, ramp
from svorf.optim import parse_probe
from svorf.ray_sampling import (
    OBJECT_HEAVY_FRACTION,
    RAY_SAMPLING,
    SALIENT_RAY_SAMPLING,
    STATEFUL_RAY_SAMPLING,
)
from svorf.registry import PRESETS, PresetSpec, Recipe, recipe_for

__all__ = [
    "BOOKKEEPING_FIELDS",
    "CPU_RECIPE",
    "CPU_RECIPE_MODEL_FIELDS",
    "CPU_RECIPE_PRESETS",
    "LR_DECAYS",
    "PRESETS",
    "PROGRESS_FIELDS",
    "SCALES",
    "PresetSpec",
    "TrainConfig",
    "apply_recipe",
    "config_key",
    "learning_fields",
    "lr_at",
    "recipe_applies",
    "recipe_of",
    "resolve_device",
    "run_configs",
    "train_config",
]

#: Learning-rate schedules after warm-up (``TrainConfig.lr_decay``).
LR_DECAYS = ("none", "cosine")

#: Fields whose effect follows the run's progress through the rays and views of a step
#: (:meth:`TrainConfig.salient_share`, :meth:`~TrainConfig.input_view_targeted`,
#: :meth:`~TrainConfig.ray_stride`, which read these and no others, as a test checks); the
#: learning rate follows it too when ``lr_decay`` is not ``"none"``. Resuming a run under
#: another time budget would replay them (``svorf.checkpoint.check_resumable_budget``).
PROGRESS_FIELDS: tuple[str, ...] = ("salient_fade", "input_view_from", "coarse_to_fine")


@dataclass(frozen=True)
class TrainConfig:
    """Optimisation and bookkeeping settings of one training run (saved as JSON)."""

    steps: int = 1000
    """Optimizer steps in total (a resumed run continues up to this number)."""
    batch_scenes: int = 1
    """Scenes per step (B); one input view each. Paper: 16 (2 per GPU on 8 GPUs)."""
    rays_per_scene: int = 64
    """Target rays per scene per step (R). Paper: 64."""
    lr: float = 1e-4
    """Adam learning rate after warm-up. Paper: 1e-4."""
    betas: tuple[float, float] = (0.9, 0.999)
    """Adam betas. Paper: (0.9, 0.999)."""
    warmup: int = 1000
    """Linear learning-rate warm-up steps (lr * step / warmup). Paper: 1,000."""
    lr_decay: str = "none"
    """Learning rate after warm-up: "none" (constant; the paper and the cpu recipe) or
    "cosine": a half cosine from ``lr`` down to ``lr * lr_final_ratio`` over the run. The run's
    progress is the larger of ``step / steps`` and, in a time-budgeted run
    (``train(max_wall_s=...)``), its training wall time over the budget, so a budgeted
    run reaches the low rate when its time runs out whatever its speed."""
    lr_final_ratio: float = 0.05
    """Final learning rate over ``lr`` of ``lr_decay="cosine"``."""
    lr_decay_from: float = 0.0
    """Progress (as for ``lr_decay``) where the cosine starts: the rate stays ``lr`` until
    then and falls to ``lr * lr_final_ratio`` over the rest of the run (0 = over the whole
    run). A late decay keeps the full rate for most of the run and settles the weights at
    its end. Keyed only when set."""
    seed: int = 0
    """Seeds parameter init, data sampling and the model's own randomness."""
    ray_sampling: str = "uniform"
    """Ray-sampling strategy, a name in ``svorf.ray_sampling.RAY_SAMPLING``; "uniform" = paper,
    "object_heavy" (cpu scale) = half the rays from salient pixels, "object_heavy_ring" = the
    same with the salient pixels grown by one pixel, "object_balanced" = the
    same half shared equally among the salient pixels' blobs, "error_driven" = half
    the rays from image tiles in proportion to the model's recent error there
    (``svorf.ray_sampling.ErrorMap``; label-free, its state is checkpointed)."""
    salient_fade: tuple[float, float] | None = None
    """``(p0, p1)``: the salient share of a salient strategy's rays
    (``svorf.ray_sampling.SALIENT_RAY_SAMPLING``, e.g. "object_heavy") fades linearly from
    its default to 0 between progress ``p0`` and ``p1`` (progress as for ``lr_decay``), so
    the rays end uniform and the loss ends the paper's per-pixel mean. Salient rays weigh
    an object's edge pixels about 1.8x the floor pixels beside them (measured on cpu-scale
    CLEVR-567 training scenes), which pays a model to grow its objects into the floor.
    None = the strategy's share throughout. A lever (docs/notes/cpu_recipe.md)."""
    input_view_from: float | None = None
    """Progress (as for ``lr_decay``) from which the input view is one of the target views
    of the novel-view setup (``ModelConfig.nvs``): its pixels join the other views' as
    candidates for each scene's rays, as uORF reconstructs every view, the input
    included. The input view's segmentation (ARI, FG-ARI) is then fitted directly, not
    only through the other views. None = never (the paper's novel-view setup: rays from
    the other views only). A lever (docs/notes/cpu_recipe.md)."""
    pixel_jitter: float = 0.0
    """Where inside its pixel a training ray passes: through a point drawn uniformly from a
    square of this side (in pixels) around the pixel centre, the target still the pixel's
    colour. 0 = the centre (the paper). 1 = anywhere in the pixel: the field is fitted to
    the pixel's area, as the camera's pixel integrates it, not to one point per pixel, so
    between two pixel centres an edge is supervised rather than left to the fields'
    interpolation. Evaluation and rendering keep the centres. A lever
    (docs/notes/cpu_recipe.md)."""
    gray_scenes: float = 0.0
    """The chance that a training scene is shown colour-free for one step: its input view
    and its target rays in Rec.601 luma (``0.299 R + 0.587 G + 0.114 B`` in all three
    channels, as ``generate``'s clevr567-gray test split). 0 = never (the paper, which
    trains on RGB only). Against the encoder's failure on grayscale test images, which
    loses objects of every size and contrast. A lever (docs/notes/cpu_recipe.md)."""
    coarse_to_fine: tuple[int, float] | None = None
    """``(stride, until)``: uORF's coarse-to-fine. Before progress ``until`` (as for
    ``lr_decay``) every training ray goes through the centre of a ``stride`` x ``stride``
    block of its view and its target is the block's mean colour, as a camera of
    ``1/stride`` the resolution sees it (the ray strategy draws on those area-averaged
    views); from ``until`` on, pixels at full resolution. Early steps fit a blurred scene,
    layout before edges. The views' sides must be multiples of ``stride``. None = full
    resolution throughout (the paper). A lever (docs/notes/cpu_recipe.md)."""
    nvs_warmup: int = 0
    """Input-view reconstruction warm-up (cpu recipe, docs/notes/cpu_recipe.md): for the first
    this many steps the target rays come from the input view itself, afterwards from the
    other views (novel-view supervision, when ``ModelConfig.nvs``). 0 = paper (novel views
    from step 0)."""
    log_every: int = 10
    """Append a line to log.jsonl every this many steps (and at the last step)."""
    ckpt_every: int = 500
    """Write checkpoint.pt every this many steps (and at the last step)."""
    eval_every: int = 0
    """Run the held-out evaluation every this many steps; 0 = never."""
    eval_scenes: int = 4
    """Held-out scenes used by each evaluation."""
    device: str = "auto"
    """"auto" (CUDA when available, else CPU), "cpu", "cuda" or "cuda:N"."""
    target_size: int | None = None
    """Resolution of the images the training rays are drawn from (square; the training split
    must hold at least it), above the encoder's ``ModelConfig.image_size``: the encoder
    still sees the input view area-averaged down to ``image_size``, while the target rays
    and colours come from the finer grid, so an object's edge is supervised at
    sub-pixel detail of the evaluation resolution and a step costs the same (same rays,
    same encoder input). Evaluation and rendering stay at ``image_size``. None =
    ``image_size`` (the paper: one resolution). A lever (docs/notes/cpu_recipe.md)."""
    ema_decay: float = 0.0
    """Keep an exponential moving average of the weights with this per-step decay
    (``svorf.optim.WeightAverage``; 0 = off, the paper). Training itself is unchanged;
    checkpoints also hold the average (``model_ema``) and ``load_run`` evaluates it unless
    asked for the raw weights, so one run scores both. A lever (docs/notes/cpu_recipe.md)."""
    average_probes: tuple[str, ...] = ()
    """Extra weight averages kept beside the run for comparison, never used by it nor
    scored unless asked for: ``"emaD"`` an exponential moving average with decay D
    (``svorf.optim.WeightAverage``), ``"tailP"`` the uniform mean of the weights from the
    fraction P of the run on (``svorf.optim.TailAverage``). Checkpoints hold them
    (``model_average_probes``); ``load_run(weights=NAME)`` and ``diagnose --weights NAME``
    score one, so a single run compares them with its ``ema_decay`` average and its own
    weights at the same steps. Training is unchanged. () = none (every scale)."""
    enc_lr_scale: float = 1.0
    """The learning rate of the slot inference (the image encoder and the slot decoder:
    ``SVORF.encoder``, ``SVORF.slot_module``) as a multiple of ``lr`` at every step, warm-up
    and decay included; every other parameter keeps ``lr``. 1 = one rate for all (the
    paper). A lever (docs/notes/cpu_recipe.md)."""
    slot_distill: tuple[float, int, float] | None = None
    """``(weight, steps, lr)``: teach the slot inference what iterative inference finds.
    From the end of ``nvs_warmup`` on, every step's slots are refined ``steps`` Adam steps
    at ``lr`` on that step's own target rays (every network frozen, deterministic samples,
    photometric MSE; ``svorf.refine.refine_batch``), and ``weight`` times the mean squared
    distance of the encoder's slots to the refined ones (a fixed target) joins the loss.
    The encoder is still all that infers slots at evaluation. It reads only the training
    rays, so training stays unsupervised. None = off (the paper). Keyed only when set. A
    lever (docs/notes/cpu_recipe.md)."""
    refine_train: tuple[int, float, int] | None = None
    """``(steps, lr, rays)``: iterative inference inside training. From the end of
    ``nvs_warmup`` on, every step's slots are refined ``steps`` Adam steps at ``lr`` on
    ``rays`` random pixels of each scene's *input* view (every network frozen,
    deterministic samples, photometric MSE; ``svorf.refine.refine_batch``), as the
    evaluation's ``--refine-slots`` refines them, and the step's target rays are rendered
    from the refined slots. The encoder's gradient passes the refinement as the identity
    (first order), so the fields learn to decode refined slots and the encoder learns
    where refinement starts from. Meant to be evaluated with refinement. It reads only
    the input view's pixels, so training stays unsupervised. None = off (the paper).
    Keyed only when set. A lever (docs/notes/cpu_recipe.md)."""

    def __post_init__(self) -> None:
        object.__setattr__(self, "betas", tuple(float(b) for b in self.betas))
        for name in (
            "steps",
            "batch_scenes",
            "rays_per_scene",
            "log_every",
            "ckpt_every",
            "eval_scenes",
        ):
            if int(getattr(self, name)) < 1:
                raise ValueError(f"TrainConfig.{name} must be >= 1, got {getattr(self, name)}")
        if self.warmup < 0 or self.eval_every < 0 or self.nvs_warmup < 0:
            raise ValueError("TrainConfig.warmup, eval_every and nvs_warmup must be >= 0")
        if self.lr_decay not in LR_DECAYS:
            raise ValueError(
                f"TrainConfig.lr_decay must be one of {list(LR_DECAYS)}, got {self.lr_decay!r}"
            )
        if not 0.0 <= self.lr_final_ratio <= 1.0:
            raise ValueError(
                f"TrainConfig.lr_final_ratio must be in [0, 1], got {self.lr_final_ratio}"
            )
        object.__setattr__(self, "lr_decay_from", float(self.lr_decay_from))
        if not 0.0 <= self.lr_decay_from < 1.0:
            raise ValueError(
                "TrainConfig.lr_decay_from must be a progress in [0, 1) (where the cosine "
                f"starts), got {self.lr_decay_from}"
            )
        if self.lr_decay_from and self.lr_decay != "cosine":
            raise ValueError(
                f"TrainConfig.lr_decay_from={self.lr_decay_from} needs lr_decay='cosine' "
                f"(got {self.lr_decay!r}): it says where the cosine starts"
            )
        if not (self.lr > 0 and math.isfinite(self.lr)):
            raise ValueError(f"TrainConfig.lr must be a positive number, got {self.lr}")
        if len(self.betas) != 2 or not all(0.0 <= b < 1.0 for b in self.betas):
            raise ValueError(f"TrainConfig.betas must be two numbers in [0, 1), got {self.betas}")
        if self.slot_distill is not None:
            try:
                w, n, rate = (float(x) for x in self.slot_distill)
            except (TypeError, ValueError):  # not three numbers
                w = n = rate = 0.0
            if not (w > 0 and n == int(n) and n >= 1 and rate > 0):
                raise ValueError(
                    "TrainConfig.slot_distill must be (weight > 0, refinement steps >= 1, "
                    f"refinement lr > 0), got {self.slot_distill}"
                )
            object.__setattr__(self, "slot_distill", (float(w), int(n), float(rate)))
        if self.average_probes:
            names = tuple(str(x) for x in self.average_probes)
            for name in names:
                try:
                    parse_probe(name)
                except ValueError as e:
                    raise ValueError(f"TrainConfig.average_probes: {e}") from None
            if len(set(names)) != len(names):
                raise ValueError(f"TrainConfig.average_probes: a name repeats in {list(names)}")
            object.__setattr__(self, "average_probes", names)
        if self.refine_train is not None:
            try:
                n, rate, r = (float(x) for x in self.refine_train)
            except (TypeError, ValueError):  # not three numbers
                n = rate = r = 0.0
            if not (n == int(n) and n >= 1 and rate > 0 and r == int(r) and r >= 1):
                raise ValueError(
                    "TrainConfig.refine_train must be (refinement steps >= 1, refinement "
                    f"lr > 0, input-view rays >= 1), got {self.refine_train}"
                )
            if self.slot_distill is not None:
                raise ValueError(
                    "TrainConfig.refine_train and slot_distill refine the slots in two "
                    "different ways; set one of them"
                )
            object.__setattr__(self, "refine_train", (int(n), float(rate), int(r)))
        object.__setattr__(self, "enc_lr_scale", float(self.enc_lr_scale))
        if not (math.isfinite(self.enc_lr_scale) and self.enc_lr_scale > 0.0):
            raise ValueError(
                f"TrainConfig.enc_lr_scale must be a positive number (1 = one learning rate "
                f"for all), got {self.enc_lr_scale}"
            )
        if not 0.0 <= self.ema_decay < 1.0:
            raise ValueError(f"TrainConfig.ema_decay must be in [0, 1), got {self.ema_decay}")
        if self.target_size is not None and int(self.target_size) < 8:
            raise ValueError(
                f"TrainConfig.target_size must be None or >= 8 pixels, got {self.target_size}"
            )
        object.__setattr__(self, "pixel_jitter", float(self.pixel_jitter))
        if not 0.0 <= self.pixel_jitter <= 1.0:
            raise ValueError(
                "TrainConfig.pixel_jitter must be in [0, 1] (pixels; 0 = through the pixel "
                f"centre, 1 = anywhere in the pixel), got {self.pixel_jitter}"
            )
        object.__setattr__(self, "gray_scenes", float(self.gray_scenes))
        if not 0.0 <= self.gray_scenes <= 1.0:
            raise ValueError(
                "TrainConfig.gray_scenes must be a probability in [0, 1] (0 = every scene in "
                f"colour), got {self.gray_scenes}"
            )
        if self.input_view_from is not None:
            object.__setattr__(self, "input_view_from", float(self.input_view_from))
            if not 0.0 <= self.input_view_from <= 1.0:
                raise ValueError(
                    "TrainConfig.input_view_from must be None or a fraction of the run in "
                    f"[0, 1], got {self.input_view_from}"
                )
        if self.coarse_to_fine is not None:
            c2f = tuple(self.coarse_to_fine)
            if len(c2f) != 2 or int(c2f[0]) < 2 or not 0.0 <= float(c2f[1]) <= 1.0:
                raise ValueError(
                    "TrainConfig.coarse_to_fine must be None or (stride, until) with stride "
                    f">= 2 pixels and until a fraction of the run in [0, 1], got {c2f}"
                )
            # JSON gives a list; the key and equality want the tuple.
            object.__setattr__(self, "coarse_to_fine", (int(c2f[0]), float(c2f[1])))
            if self.pixel_jitter or self.ray_sampling in STATEFUL_RAY_SAMPLING:
                raise ValueError(
                    "TrainConfig.coarse_to_fine draws block centres; it does not combine with "
                    f"pixel_jitter={self.pixel_jitter} or ray_sampling={self.ray_sampling!r} "
                    "(per-pixel error maps): set pixel_jitter=0 and another ray_sampling, or "
                    "coarse_to_fine=None"
                )
        if self.ray_sampling not in RAY_SAMPLING:
            raise ValueError(
                f"TrainConfig.ray_sampling must be one of {sorted(RAY_SAMPLING)}, "
                f"got {self.ray_sampling!r}"
            )
        if self.salient_fade is not None:
            fade = tuple(float(x) for x in self.salient_fade)  # JSON gives a list
            object.__setattr__(self, "salient_fade", fade)
            if len(fade) != 2 or not 0.0 <= fade[0] <= fade[1] <= 1.0:
                raise ValueError(
                    "TrainConfig.salient_fade must be (p0, p1) with 0 <= p0 <= p1 <= 1 "
                    f"(fractions of the run), got {self.salient_fade}"
                )
            if self.ray_sampling not in SALIENT_RAY_SAMPLING:
                raise ValueError(
                    f"TrainConfig.salient_fade fades the salient share of one of "
                    f"{sorted(SALIENT_RAY_SAMPLING)}; ray_sampling={self.ray_sampling!r} has "
                    "none: set salient_fade=None or choose one of those strategies"
                )

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready dict of every field (``betas`` as a list), as checkpoints store it;
        ``target_size``, ``salient_fade``, ``input_view_from``, ``pixel_jitter``, ``gray_scenes``,
        ``coarse_to_fine``, ``ema_decay``, ``enc_lr_scale``, ``lr_decay_from``,
        ``slot_distill``, ``refine_train`` and ``average_probes`` only when set, so that the keys of earlier
        runs stay valid."""
        d = dataclasses.asdict(self)
        d["betas"] = list(self.betas)
        if d["salient_fade"] is None:
            del d["salient_fade"]
        else:
            d["salient_fade"] = list(d["salient_fade"])
        if d["target_size"] is None:
            del d["target_size"]
        if not d["ema_decay"]:
            del d["ema_decay"]
        if d["enc_lr_scale"] == 1.0:
            del d["enc_lr_scale"]
        if not d["lr_decay_from"]:
            del d["lr_decay_from"]
        if d["slot_distill"] is None:
            del d["slot_distill"]
        else:
            d["slot_distill"] = list(d["slot_distill"])
        if not d["average_probes"]:
            del d["average_probes"]
        else:
            d["average_probes"] = list(d["average_probes"])
        if d["refine_train"] is None:
            del d["refine_train"]
        else:
            d["refine_train"] = list(d["refine_train"])
        if d["input_view_from"] is None:
            del d["input_view_from"]
        if not d["pixel_jitter"]:
            del d["pixel_jitter"]
        if not d["gray_scenes"]:
            del d["gray_scenes"]
        if d["coarse_to_fine"] is None:
            del d["coarse_to_fine"]
        else:
            d["coarse_to_fine"] = list(d["coarse_to_fine"])
        return d

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> TrainConfig:
        """The config of :meth:`to_dict`'s dict; fields it lacks take their defaults.

        Raises:
            ValueError: an unknown key, or a value the checks of the fields refuse.
        """
        names = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(d) - names)
        if unknown:
            raise ValueError(f"TrainConfig.from_dict: unknown keys {unknown}")
        return cls(**d)

    def salient_share(self, progress: float) -> float | None:
        """The salient share of the rays at ``progress`` under ``salient_fade`` (None: off,
        the strategy's own share)."""
        if self.salient_fade is None:
            return None
        return OBJECT_HEAVY_FRACTION * (1.0 - ramp(progress, *self.salient_fade))

    def input_view_targeted(self, progress: float) -> bool:
        """Whether the input view is among the target views at ``progress``
        (``input_view_from``)."""
        return self.input_view_from is not None and progress >= self.input_view_from

    def ray_stride(self, progress: float) -> int:
        """The block side of the training rays at ``progress`` (``coarse_to_fine``; 1 =
        full-resolution pixels)."""
        c2f = self.coarse_to_fine
        return c2f[0] if c2f is not None and progress < c2f[1] else 1

    def replace(self, **changes: Any) -> TrainConfig:
        """A copy with ``changes`` (field values) applied and checked."""
        return dataclasses.replace(self, **changes)


#: Scale names (``svorf.registry.SCALE_NAMES``).
SCALES: tuple[str, ...] = registry.SCALE_NAMES

#: TrainConfig fields that do not change what a run learns (where and how often it logs,
#: checkpoints and evaluates, and on which device): left out of :func:`config_key` and of
#: the benchmark's model cache key.
BOOKKEEPING_FIELDS: tuple[str, ...] = (
    "device",
    "log_every",
    "ckpt_every",
    "eval_every",
    "eval_scenes",
)


def train_config(scale: str, preset: str = "clevr567", **overrides: Any) -> TrainConfig:
    """The training settings of a scale (from the registry, ``svorf.registry.SCALES``).

    Args:
        scale: "smoke" (tests: seconds), "cpu" (a 2-core machine, about an hour at 64x64;
            object-heavy ray sampling; its recipe decomposes held-out CLEVR-567 in 60
            minutes on a machine of about 35,000 steps an hour, docs/notes/cpu_recipe.md) or
            "paper" (the paper's optimiser, uniform rays, 64 rays per scene).
        preset: a key of :data:`PRESETS` (checked; all presets share the settings today).
        **overrides: any TrainConfig field.

    This is the scale's schedule without the recipe; :func:`run_configs` gives what
    ``svorf train --scale S --preset P`` trains.

    The paper gives Adam 1e-4, betas (0.9, 0.999), 1,000 warm-up steps, 64 rays per scene
    and batch 16 on 8 GPUs for ~7 h; it does not give the number of steps. 150k is an
    assumption of ~0.17 s per step over those 7 h.
    """
    choose(preset, sorted(PRESETS), "preset")
    spec = registry.SCALES[choose(scale, SCALES, "scale")]
    return TrainConfig(**spec.train).replace(**overrides)


_CPU = registry.SCALES["cpu"].recipe
assert _CPU is not None  # the cpu scale has its recipe

#: The cpu recipe (docs/notes/cpu_recipe.md; ``svorf.registry.SCALES["cpu"].recipe``): what
#: the ``cpu`` scale changes on top of :func:`train_config` / ``svorf.config.model_config``
#: for the CLEVR-567 family and Room-Chair (:data:`CPU_RECIPE_PRESETS`), train fields then
#: model fields.
#: ``svorf train --scale cpu`` and ``benchmark --scale cpu`` both get it through
#: :func:`run_configs`.
CPU_RECIPE: dict[str, Any] = _CPU.fields

#: The :data:`CPU_RECIPE` keys that are ModelConfig fields.
CPU_RECIPE_MODEL_FIELDS: tuple[str, ...] = tuple(_CPU.model)

#: Training presets whose ``cpu``-scale runs use :data:`CPU_RECIPE`.
CPU_RECIPE_PRESETS: tuple[str, ...] = _CPU.presets


def recipe_applies(scale: str, preset: str) -> bool:
    """Whether :func:`run_configs` adds the scale's recipe for this scale and preset."""
    return scale in registry.SCALES and recipe_for(scale, preset) is not None


def apply_recipe(
    mcfg: ModelConfig,
    tcfg: TrainConfig,
    levers: dict[str, Any] | None = None,
    recipe: Recipe = _CPU,
    preset: str | None = None,
) -> tuple[ModelConfig, TrainConfig]:
    """``(mcfg, tcfg)`` with ``recipe`` (default the cpu recipe, :data:`CPU_RECIPE`) applied,
    with the fields it sets for training preset ``preset`` alone (``Recipe.preset_model``;
    None: none), its entries replaced by ``levers`` (any model or train field, named by the
    recipe or not). Levers that turn ``slot_locality`` off also turn off the recipe's
    ``slot_locality_narrow`` and ``slot_locality_xy`` (that radius's schedule and shape)
    unless they set them themselves."""
    lv = {**recipe.fields_for(preset), **(levers or {})}
    if lv.get("slot_locality") is None:
        for name in ("slot_locality_narrow", "slot_locality_xy"):
            if name not in (levers or {}):
                lv.pop(name, None)
    model_names = {f.name for f in dataclasses.fields(ModelConfig)}
    model_kw = {k: lv.pop(k) for k in list(lv) if k in model_names}
    return mcfg.replace(**model_kw), tcfg.replace(**lv)


def run_configs(
    scale: str,
    preset: str,
    image_size: int | None = None,
    *,
    recipe: bool = True,
    **train_overrides: Any,
) -> tuple[ModelConfig, TrainConfig]:
    """The (model, train) configs of a ``svorf train --scale S --preset P`` run.

    The scale's sizes and schedule and the preset's slots come from ``svorf.registry``;
    at the ``cpu`` scale the CLEVR-567 family and Room-Chair (:data:`CPU_RECIPE_PRESETS`) get the cpu
    recipe (:data:`CPU_RECIPE`) unless ``recipe=False``; ``train_overrides`` (any
    TrainConfig field) are applied last. This is the one place that decides a scale's
    configs: the benchmark's ``--scale`` goes through it too.
    """
    choose(preset, sorted(PRESETS), "preset")
    choose(scale, SCALES, "scale")
    spec = PRESETS[preset]
    mcfg = model_config(scale, num_slots=spec.num_slots, image_size=image_size)
    if spec.slot_mask_train:
        mcfg = mcfg.replace(slot_mask_train=spec.slot_mask_train)
    tcfg = train_config(scale, preset)
    scale_recipe = recipe_for(scale, preset) if recipe else None
    if scale_recipe is not None:
        mcfg, tcfg = apply_recipe(mcfg, tcfg, recipe=scale_recipe, preset=preset)
    return mcfg, tcfg.replace(**train_overrides)


def recipe_of(mcfg: ModelConfig, tcfg: TrainConfig) -> Recipe | None:
    """The recipe whose model these configs train, at its scale's image size (None: none).

    The configs are a recipe's when the model config is that of a ``svorf train --scale S
    --preset P`` run of a recipe preset and the train config differs from its at most in
    the step count and the seed (what ``--steps``, ``--seed`` and ``benchmark
    --train-minutes`` change). A variant of the recipe (an ablation, another resolution)
    costs another amount per step, so its speed says nothing about the recipe's.
    """

    def schedule(t: TrainConfig) -> dict[str, Any]:
        return learning_fields(t.replace(steps=1, seed=0))

    for scale, spec in registry.SCALES.items():
        for preset in spec.recipe.presets if spec.recipe is not None else ():
            ref_m, ref_t = run_configs(scale, preset)
            if mcfg == ref_m and schedule(tcfg) == schedule(ref_t):
                return spec.recipe
    return None


def learning_fields(tcfg: TrainConfig) -> dict[str, Any]:
    """``tcfg.to_dict()`` without the :data:`BOOKKEEPING_FIELDS`: what changes the learning."""
    return {k: v for k, v in tcfg.to_dict().items() if k not in BOOKKEEPING_FIELDS}


def config_key(mcfg: ModelConfig, tcfg: TrainConfig) -> str:
    """16 hex digits that name what a run with these configs learns.

    The SHA-256 of the canonical JSON (sorted keys, no spaces) of ``{"model":
    mcfg.to_dict(), "train": learning_fields(tcfg)}``: two runs with the same key train the
    same model (same architecture, schedule and seed) whatever their device or logging.
    ``svorf config`` prints it, and ``benchmark run ... --show-config`` prints it for every
    model a protocol trains. It does not name the data (the benchmark's run key adds the
    dataset's fingerprint).

    Example:
        >>> m, t = run_configs("cpu", "clevr567")
        >>> config_key(m, t) == config_key(m, t.replace(device="cuda", log_every=1))
        True
    """
    src = {"model": mcfg.to_dict(), "train": learning_fields(tcfg)}
    text = json.dumps(src, sort_keys=True, separators=(",", ":"), allow_nan=False)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def resolve_device(name: str = "auto") -> torch.device:
    """Device for a name: "auto" = CUDA when available, else CPU; others go to torch.device."""
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    dev = torch.device(name)
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise ValueError(f"device {name!r} requested but CUDA is not available")
    return dev


def lr_at(cfg: TrainConfig, step: int, progress: float | None = None) -> float:
    """Learning rate of optimizer step ``step`` (0-based): linear warm-up, then constant
    (``lr_decay="none"``) or a half cosine to ``lr * lr_final_ratio`` (``"cosine"``) over
    the progress from ``lr_decay_from`` to 1.

    ``progress`` in [0, 1] is how far the run is (default ``step / steps``; a time-budgeted
    run passes the larger of that and its wall-time fraction).
    """
    if cfg.warmup and step < cfg.warmup:
        return cfg.lr * (step + 1) / cfg.warmup
    if cfg.lr_decay == "cosine":
        p = step / cfg.steps if progress is None else progress
        p0 = cfg.lr_decay_from
        p = min(max((float(p) - p0) / (1.0 - p0), 0.0), 1.0)
        r = cfg.lr_final_ratio
        return cfg.lr * (r + (1.0 - r) * 0.5 * (1.0 + math.cos(math.pi * p)))
    return cfg.lr
