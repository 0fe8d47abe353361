"""Training loop, checkpoints, run loading and per-scene prediction for sVORF.

Where this sits: ``svorf.data`` (dataset + ray sampler) -> **here** (Adam with linear
warm-up, paper appendix A) -> checkpoints in a run folder -> ``load_run`` /
``predict_scene`` for ``svorf render`` and the benchmark adapter.

A run folder holds::

    checkpoint.pt   latest good state (atomic temp + os.replace): model, optimizer, step,
                    RNG states, configs as JSON dicts, dataset fingerprint
    config.json     the same configs, for people
    log.jsonl       one line per logged step: step, wall_s, lr, loss, parts, steps_per_s
    eval.jsonl      one line per held-out evaluation: step, wall_s, metrics
    summary.json    the dict :func:`train` returns

Determinism: parameters are initialised after ``torch.manual_seed(seed)``; scenes,
input views and rays come from a ``torch.Generator`` seeded with ``seed``; the model's
own randomness (stratified sampling jitter, the packed-11 slot mask) uses the global
torch RNG. All of these states are checkpointed, so ``resume=True`` continues the
uninterrupted run step for step (bit-identical on the same machine and device).

Data parallel: under ``torchrun`` (a process group initialised by ``svorf.cli`` through
``svorf.distributed.init_from_env``) :func:`train` splits every step's global batch of
``batch_scenes`` scenes over the ranks and averages the gradients; rank 0 writes the run
folder. The result matches a single-process run with the same configs up to float
summation order (see ``svorf.distributed`` for how the random draws are kept identical).

Nothing here imports ``benchmark`` or ``generators`` (svorf stands alone): held-out
metrics such as ARI are plugged in by the caller through ``eval_fn``.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import re
import resource
import sys
import tempfile
import time
from collections.abc import Callable
from contextlib import nullcontext
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

from scenefmt import atomic_write_bytes, atomic_write_json
from scenefmt.cli_util import choose
from svorf import distributed
from svorf.config import ModelConfig, bf16_autocast_on, model_config
from svorf.data import RAY_SAMPLING, MultiViewDataset, RayBatch, RaySampler, dataset_fingerprint
from svorf.model import SVORF

__all__ = [
    "CPU_RECIPE",
    "CPU_RECIPE_MODEL_FIELDS",
    "CPU_RECIPE_PRESETS",
    "PRESETS",
    "CheckpointError",
    "PresetSpec",
    "RunInfo",
    "TrainConfig",
    "TrainingDiverged",
    "apply_recipe",
    "dataset_fingerprint",
    "default_eval",
    "init_weights_from",
    "load_run",
    "predict_scene",
    "read_checkpoint",
    "recipe_applies",
    "resolve_device",
    "run_configs",
    "train",
    "train_config",
]

CHECKPOINT_NAME = "checkpoint.pt"
CHECKPOINT_FORMAT = "svorf-checkpoint-1"

#: Signature of a held-out evaluation hook: ``eval_fn(model, dataset) -> {name: float}``.
#: The model is in eval mode and the global RNG is forked around the call.
EvalFn = Callable[[SVORF, MultiViewDataset], dict[str, float]]


class CheckpointError(ValueError):
    """A run folder without a readable checkpoint; the message is one line."""


class TrainingDiverged(RuntimeError):
    """The loss or a gradient became NaN/Inf; the last good checkpoint is left untouched."""


# --------------------------------------------------------------------------- configs


#: Learning-rate schedules after warm-up (``TrainConfig.lr_decay``).
LR_DECAYS = ("none", "cosine")


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
    """Learning rate after warm-up: "none" (constant, paper) or "cosine" (cpu recipe): a
    half cosine from ``lr`` down to ``lr * lr_final_ratio`` over the run. The run's
    progress is the larger of ``step / steps`` and, in a time-budgeted run
    (``train(max_wall_s=...)``), its training wall time over the budget, so a budgeted
    run reaches the low rate when its time runs out whatever its speed."""
    lr_final_ratio: float = 0.05
    """Final learning rate over ``lr`` of ``lr_decay="cosine"``."""
    seed: int = 0
    """Seeds parameter init, data sampling and the model's own randomness."""
    ray_sampling: str = "uniform"
    """Ray-sampling strategy, a name in ``svorf.data.RAY_SAMPLING``; "uniform" = paper,
    "object_heavy" (cpu scale) = half the rays from salient pixels, "error_driven" = half
    the rays from image tiles in proportion to the model's recent error there
    (``svorf.data.ErrorMap``; label-free, its state is checkpointed)."""
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
        if not (self.lr > 0 and math.isfinite(self.lr)):
            raise ValueError(f"TrainConfig.lr must be a positive number, got {self.lr}")
        if len(self.betas) != 2 or not all(0.0 <= b < 1.0 for b in self.betas):
            raise ValueError(f"TrainConfig.betas must be two numbers in [0, 1), got {self.betas}")
        if self.ray_sampling not in RAY_SAMPLING:
            raise ValueError(
                f"TrainConfig.ray_sampling must be one of {sorted(RAY_SAMPLING)}, "
                f"got {self.ray_sampling!r}"
            )

    def to_dict(self) -> dict[str, Any]:
        d = dataclasses.asdict(self)
        d["betas"] = list(self.betas)
        return d

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> TrainConfig:
        names = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(d) - names)
        if unknown:
            raise ValueError(f"TrainConfig.from_dict: unknown keys {unknown}")
        return cls(**d)

    def replace(self, **changes: Any) -> TrainConfig:
        return dataclasses.replace(self, **changes)


#: Fields that may differ between a checkpoint and the config that resumes it.
_RESUMABLE_CHANGES = {"steps", "log_every", "ckpt_every", "eval_every", "eval_scenes", "device"}


@dataclass(frozen=True)
class PresetSpec:
    """What a training preset fixes: slots, slot masking and which data it trains on."""

    num_slots: int
    data_presets: tuple[str, ...]
    slot_mask_train: int = 0
    init_from: str | None = None
    """Training preset whose model starts this one (paper appendix A: "we initialize our
    models for Room-Diverse using weights from a model that have previously been trained on
    the CLEVR-567 dataset"); the benchmark trains that model first and passes its run as
    ``train(init_from=...)``; ``svorf train --init-from RUN`` does the same by hand."""


#: Training presets. The paper's K per dataset (appendix A): 8 for CLEVR-567, 5 for the
#: Room datasets; the packed-CLEVR-11 setting trains on CLEVR-567 with 11 slots, 4 of them
#: masked off per step. "synthetic" is the test split of
#: ``svorf.synthetic`` (2-3 spheres).
PRESETS: dict[str, PresetSpec] = {
    "clevr567": PresetSpec(8, ("clevr567",)),
    "clevr567-heldout": PresetSpec(8, ("clevr567-heldout",)),
    "packed-clevr11": PresetSpec(11, ("clevr567",), slot_mask_train=4),
    "room-chair": PresetSpec(5, ("room-chair",)),
    "room-diverse": PresetSpec(5, ("room-diverse",), init_from="clevr567"),
    "synthetic": PresetSpec(4, ("synthetic",)),
}

SCALES = ("smoke", "cpu", "paper")


def train_config(scale: str, preset: str = "clevr567", **overrides: Any) -> TrainConfig:
    """Registry of training settings.

    Args:
        scale: "smoke" (tests: seconds), "cpu" (a 2-core machine, about an hour at 64x64;
            object-heavy ray sampling; a first guess, not yet shown to decompose) or
            "paper" (the paper's optimiser, uniform rays, 64 rays per scene).
        preset: a key of :data:`PRESETS` (checked; all presets share the settings today).
        **overrides: any TrainConfig field.

    The paper gives Adam 1e-4, betas (0.9, 0.999), 1,000 warm-up steps, 64 rays per scene
    and batch 16 on 8 GPUs for ~7 h; it does not give the number of steps. 150k is an
    assumption of ~0.17 s per step over those 7 h.
    """
    choose(preset, sorted(PRESETS), "preset")
    if scale == "smoke":
        base = TrainConfig(
            steps=30,
            batch_scenes=2,
            rays_per_scene=64,
            lr=1e-3,
            warmup=5,
            log_every=5,
            ckpt_every=15,
        )
    elif scale == "cpu":
        # ~1 h on 2 cores: one step of the cpu model (K=8, 16+16 samples) at 4 x 128 rays
        # took 1.2-1.9 s on a shared, overloaded 2-core Xeon (4 x 256: 2.6-3.1 s), about
        # 0.9 s when the machine is quiet. Object-heavy rays because uniform rays left the
        # the calibration model of docs/notes/cpu_recipe.md on a "mean scene" plateau.
        base = TrainConfig(
            steps=4000,
            batch_scenes=4,
            rays_per_scene=128,
            lr=4e-4,
            warmup=500,
            log_every=25,
            ckpt_every=250,
            eval_every=1000,
            ray_sampling="object_heavy",
        )
    elif scale == "paper":
        base = TrainConfig(
            steps=150_000,
            batch_scenes=16,
            rays_per_scene=64,
            lr=1e-4,
            warmup=1000,
            log_every=100,
            ckpt_every=5000,
        )
    else:
        choose(scale, SCALES, "scale")  # raises: not one of SCALES
        raise AssertionError(scale)  # a scale of SCALES without a branch above
    return base.replace(**overrides)


#: The cpu recipe (docs/notes/cpu_recipe.md): what the ``cpu`` scale changes on top of
#: :func:`train_config` / ``svorf.config.model_config`` for the CLEVR-567 family
#: (:data:`CPU_RECIPE_PRESETS`). Model fields are in :data:`CPU_RECIPE_MODEL_FIELDS`; the
#: rest are TrainConfig fields. Every item is a documented config field that the
#: ``paper`` scale leaves off. ``svorf train --scale cpu`` and ``benchmark --scale cpu``
#: both get it through :func:`run_configs`.
CPU_RECIPE: dict[str, Any] = {
    "ray_sampling": "object_heavy",
    "warmup": 100,
    "nvs_warmup": 200,
    "fg_zmin": 0.05,
    "fg_box": 3.75,
    "bg_outside_fg": True,
    "comp_temperature": 1.0,
    "coord_frame": "input_azimuth",
    "slot_locality": 1.0,
    # Anchored centres (docs/notes/cpu_recipe.md, rows L, L0): "learned" centres collapsed onto
    # one spot at seed 1; anchored ones cannot, and matched or beat them at seeds 0 and 1.
    "slot_centre": "anchored",
}

#: The :data:`CPU_RECIPE` keys that are ModelConfig fields.
CPU_RECIPE_MODEL_FIELDS: tuple[str, ...] = (
    "fg_zmin",
    "fg_box",
    "bg_outside_fg",
    "comp_temperature",
    "coord_frame",
    "slot_locality",
    "slot_centre",
)

#: Training presets whose ``cpu``-scale runs use :data:`CPU_RECIPE`. The Room presets keep
#: the plain cpu scale (the recipe's locality box and floor prior are CLEVR-specific).
CPU_RECIPE_PRESETS: tuple[str, ...] = ("clevr567", "clevr567-heldout", "packed-clevr11")


def recipe_applies(scale: str, preset: str) -> bool:
    """Whether :func:`run_configs` adds :data:`CPU_RECIPE` for this scale and preset."""
    return scale == "cpu" and preset in CPU_RECIPE_PRESETS


def apply_recipe(
    mcfg: ModelConfig, tcfg: TrainConfig, levers: dict[str, Any] | None = None
) -> tuple[ModelConfig, TrainConfig]:
    """``(mcfg, tcfg)`` with :data:`CPU_RECIPE` (entries replaced by ``levers``) applied."""
    lv = {**CPU_RECIPE, **(levers or {})}
    model_kw = {k: lv.pop(k) for k in CPU_RECIPE_MODEL_FIELDS if k in lv}
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

    At the ``cpu`` scale the CLEVR-567 family (:data:`CPU_RECIPE_PRESETS`) gets the cpu
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
    if recipe and recipe_applies(scale, preset):
        mcfg, tcfg = apply_recipe(mcfg, tcfg)
    return mcfg, tcfg.replace(**train_overrides)


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
    (``lr_decay="none"``) or a half cosine to ``lr * lr_final_ratio`` (``"cosine"``).

    ``progress`` in [0, 1] is how far the run is (default ``step / steps``; a time-budgeted
    run passes the larger of that and its wall-time fraction).
    """
    if cfg.warmup and step < cfg.warmup:
        return cfg.lr * (step + 1) / cfg.warmup
    if cfg.lr_decay == "cosine":
        p = step / cfg.steps if progress is None else progress
        p = min(max(float(p), 0.0), 1.0)
        r = cfg.lr_final_ratio
        return cfg.lr * (r + (1.0 - r) * 0.5 * (1.0 + math.cos(math.pi * p)))
    return cfg.lr


# --------------------------------------------------------------------------- checkpoints


def _atomic_torch_save(obj: Any, path: Path) -> None:
    from scenefmt import default_file_mode

    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            os.fchmod(f.fileno(), default_file_mode())  # as open() gives, not mkstemp's 0600
            torch.save(obj, f)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def read_checkpoint(path: Path) -> dict[str, Any]:
    """The checkpoint dict at ``path`` (``checkpoint.pt`` of a run folder), checked.

    Raises:
        CheckpointError: missing, unreadable, or not of :data:`CHECKPOINT_FORMAT` (one line).
    """
    if not path.is_file():
        raise CheckpointError(
            f"{path}: missing - not a training run folder (make one with `svorf train --out DIR`)"
        )
    try:
        ckpt = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:
        reason = _first_line(e)
        raise CheckpointError(
            f"{path}: corrupt or unreadable checkpoint ({reason[:160]}); delete it and "
            f"retrain or restore a copy"
        ) from e
    required = ("format", "step", "model", "optimizer", "rng", "model_config", "train_config")
    if (
        not isinstance(ckpt, dict)
        or ckpt.get("format") != CHECKPOINT_FORMAT
        or any(k not in ckpt for k in required)
    ):
        raise CheckpointError(
            f"{path}: not an sVORF checkpoint of format {CHECKPOINT_FORMAT!r}; retrain"
        )
    return ckpt


@dataclass(frozen=True)
class RunInfo:
    """What a checkpoint says about its run (returned by :func:`load_run`)."""

    model: ModelConfig
    train: TrainConfig
    step: int
    dataset: dict[str, Any]
    """``fingerprint``, ``root``, ``n_scenes``, ``image_hw`` of the training data."""
    wall_s: float


def load_run(
    run_dir: str | os.PathLike, device: str | torch.device = "cpu"
) -> tuple[SVORF, RunInfo]:
    """Load the latest checkpoint of a run folder.

    Returns:
        ``(model, info)``: the model in eval mode on ``device``, and its configs.

    Raises:
        CheckpointError: the checkpoint is missing, corrupt or of another format (one line).
    """
    path = Path(run_dir) / CHECKPOINT_NAME
    ckpt = read_checkpoint(path)
    try:
        mcfg = ModelConfig.from_dict(ckpt["model_config"])
        tcfg = TrainConfig.from_dict(ckpt["train_config"])
        model = SVORF(mcfg)
        model.load_state_dict(ckpt["model"])
    except (ValueError, RuntimeError, TypeError) as e:
        msg = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
        raise CheckpointError(f"{path}: checkpoint does not match this code ({msg[:160]})") from e
    model.to(torch.device(device) if isinstance(device, str) else device).eval()
    info = RunInfo(
        mcfg, tcfg, int(ckpt["step"]), dict(ckpt.get("dataset", {})), float(ckpt.get("wall_s", 0.0))
    )
    return model, info


# --------------------------------------------------------------------------- prediction


@torch.no_grad()
def predict_scene(
    model: SVORF,
    dataset: MultiViewDataset,
    scene: int,
    input_view: int = 0,
    chunk: int = 4096,
    slots_scene: int | None = None,
) -> dict[str, Any]:
    """Encode one view of a scene and render every view at the dataset's resolution.

    Args:
        model: a trained model (any device; left in the train/eval mode it came in).
        dataset: the scenes; its resolution is the render resolution.
        scene: dataset position (``0 <= scene < len(dataset)``; ``dataset.scene_ids``
            maps positions to scene numbers).
        input_view: the view fed to the encoder.
        chunk: rays per rendering chunk (memory bound).
        slots_scene: if given, the slots come from this scene's ``input_view`` instead
            (placed in ``scene``'s input-camera frame): a control that shows how much of a
            segmentation does not depend on the scene (a fixed spatial tiling scores the
            same with another scene's slots; a decomposition does not).

    Returns:
        dict of CPU tensors and ints:
        ``rgb`` [V, H, W, 3] float32 in [0, 1]; ``depth_z`` [V, H, W] planar depth
        (world units, converted from the rendered distance t with ``z_scale``);
        ``depth_t`` [V, H, W] distance along the unit ray; ``acc`` [V, H, W] opacity;
        ``slot_probs`` [V, H, W, K] rendered soft slot masks; ``labels`` [V, H, W]
        int64 arg-max slot; ``input_view`` int; ``scene`` the scene number.
    """
    if not 0 <= scene < len(dataset):
        raise ValueError(f"scene position must be in [0, {len(dataset)}), got {scene}")
    if not 0 <= input_view < dataset.n_views:
        raise ValueError(f"input_view must be in [0, {dataset.n_views}), got {input_view}")
    device = next(model.parameters()).device
    was_training = model.training
    model.eval()
    try:
        sv = dataset[scene]
        v, (h, w) = dataset.n_views, dataset.image_hw
        src = sv if slots_scene is None else dataset[slots_scene]
        slots, extra = model.encode_for_render(src.images[input_view : input_view + 1].to(device))
        input_c2w = sv.cam_to_world[input_view : input_view + 1].to(device)
        rgb, depth_t, acc, probs = [], [], [], []
        for j in range(v):
            o = sv.rays_o[j].reshape(1, h * w, 3).to(device)
            d = sv.rays_d[j].reshape(1, h * w, 3).to(device)
            out = model.render_chunked(slots, o, d, chunk, input_c2w=input_c2w, **extra)
            rgb.append(out.rgb[0].float().cpu())
            depth_t.append(out.depth[0].float().cpu())
            acc.append(out.acc[0].float().cpu())
            probs.append(out.slot_probs[0].float().cpu())
    finally:
        model.train(was_training)
    k = probs[0].shape[-1]
    depth_t_t = torch.stack(depth_t).view(v, h, w)
    slot_probs = torch.stack(probs).view(v, h, w, k)
    return {
        "rgb": torch.stack(rgb).view(v, h, w, 3),
        "depth_z": depth_t_t * sv.z_scale,
        "depth_t": depth_t_t,
        "acc": torch.stack(acc).view(v, h, w),
        "slot_probs": slot_probs,
        "labels": slot_probs.argmax(-1),
        "input_view": input_view,
        "scene": sv.scene,
    }


def default_eval(model: SVORF, dataset: MultiViewDataset, max_scenes: int = 4) -> dict[str, float]:
    """Minimal held-out evaluation (no segmentation metrics: plug those in via ``eval_fn``).

    Renders the first ``max_scenes`` scenes from input view 0 and returns
    ``psnr_input`` (view 0), ``psnr_novel`` (the other views; PSNR of the mean MSE),
    ``depth_abs_err`` (mean |depth_z - gt| over pixels with finite ground truth) and
    ``n_scenes``.
    """
    n = min(max_scenes, len(dataset))
    mse_in, mse_nv, derr = [], [], []
    for i in range(n):
        p = predict_scene(model, dataset, i, input_view=0)
        gt = dataset.images(i).permute(0, 2, 3, 1)
        err = ((p["rgb"] - gt) ** 2).mean(dim=(1, 2, 3))
        mse_in.append(err[0])
        if len(err) > 1:
            mse_nv.append(err[1:].mean())
        gtd = dataset[i].depth_z
        ok = torch.isfinite(gtd)
        if ok.any():
            derr.append((p["depth_z"][ok] - gtd[ok]).abs().mean())

    def psnr(xs: list[Tensor]) -> float:
        return (
            float(-10.0 * torch.log10(torch.stack(xs).mean().clamp_min(1e-10))) if xs else math.nan
        )

    return {
        "psnr_input": psnr(mse_in),
        "psnr_novel": psnr(mse_nv),
        "depth_abs_err": float(torch.stack(derr).mean()) if derr else math.nan,
        "n_scenes": float(n),
    }


# --------------------------------------------------------------------------- training


def _rng_state(gen: torch.Generator, device: torch.device | None = None) -> dict[str, Any]:
    state = {
        "torch": torch.get_rng_state(),
        "cuda": torch.cuda.get_rng_state_all() if torch.cuda.is_available() else [],
        "data": gen.get_state(),
    }
    if device is not None and device.type == "cuda":
        # The generator of the device that trained: under torchrun rank r trains on
        # cuda:r, and every rank restores this state into its own device on resume.
        state["cuda_device"] = torch.cuda.get_rng_state(device)
    return state


def _set_rng_state(
    state: dict[str, Any], gen: torch.Generator, device: torch.device | None = None
) -> None:
    torch.set_rng_state(state["torch"])
    if state.get("cuda") and torch.cuda.is_available():
        torch.cuda.set_rng_state_all(state["cuda"])
    if device is not None and device.type == "cuda" and state.get("cuda_device") is not None:
        torch.cuda.set_rng_state(state["cuda_device"], device)
    gen.set_state(state["data"])


def _batch_rows(batch: RayBatch, lo: int, hi: int) -> RayBatch:
    """Scenes ``[lo, hi)`` of a batch (this rank's share of the global batch)."""
    return RayBatch(**{k: getattr(batch, k)[lo:hi] for k in batch.__dataclass_fields__})


def _truncate_jsonl(path: Path, max_step: int) -> None:
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


def _append_jsonl(path: Path, row: dict[str, Any]) -> None:
    with open(path, "a") as f:
        f.write(json.dumps(row, sort_keys=True) + "\n")


def _peak_rss_mb() -> float:
    # ru_maxrss is KiB on Linux, bytes on macOS.
    r = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return r / (1024.0 * 1024.0) if sys.platform == "darwin" else r / 1024.0


def _first_line(e: BaseException) -> str:
    """The informative line of an exception message (torch's load errors are long)."""
    lines = [re.sub(r"\x1b\[[0-9;]*m", "", x).strip() for x in str(e).splitlines()]
    lines = [x for x in lines if x]
    for x in lines:
        if "error:" in x.lower():
            return x
    return lines[0] if lines else type(e).__name__


def train(
    data_dir: str | os.PathLike,
    out_dir: str | os.PathLike,
    model_cfg: ModelConfig,
    train_cfg: TrainConfig,
    resume: bool = False,
    eval_fn: EvalFn | None = None,
    eval_data: str | os.PathLike | None = None,
    *,
    max_scenes: int | None = None,
    progress: bool = True,
    max_wall_s: float | None = None,
    init_from: str | os.PathLike | None = None,
) -> dict[str, Any]:
    """Train sVORF on a split folder and write a run folder.

    Args:
        data_dir: training split (``svorf.data.MultiViewDataset`` reads it at
            ``model_cfg.image_size``).
        out_dir: run folder (created). Holding a checkpoint already is an error unless
            ``resume``.
        model_cfg, train_cfg: the configs (saved in every checkpoint).
        resume: continue from ``out_dir/checkpoint.pt`` up to ``train_cfg.steps``; the
            model config, data and non-bookkeeping train fields must match. Without a
            checkpoint the run starts from step 0.
        eval_data: optional held-out split, evaluated every ``train_cfg.eval_every`` steps.
        eval_fn: ``fn(model, eval_dataset) -> {metric: float}``; default
            :func:`default_eval` (PSNR, depth error). Results go to ``eval.jsonl`` with
            the step and the training wall time.
        max_scenes: load only the first scenes of ``data_dir`` (quick runs).
        progress: show a tqdm bar (loss, steps/s) on stderr (rank 0 only under torchrun).
        max_wall_s: stop (with a checkpoint) once the run's training wall time, summed
            over resumed calls, reaches this many seconds, even before ``train_cfg.steps``
            (time-budgeted runs; ``resume=True`` continues them).
        init_from: a run folder or checkpoint whose weights start this run (every tensor
            whose name and shape match; see :func:`init_weights_from`), e.g. the paper's
            Room-Diverse models start from a CLEVR-567 model. Used at step 0 only; recorded
            in the checkpoint, ``config.json`` and the summary (``init_from``).

    Returns:
        Run summary: ``steps``, ``start_step``, ``final_loss``, ``wall_s`` (this call),
        ``train_wall_s`` (all calls), ``s_per_step``, ``peak_rss_mb``, ``params``,
        ``device``, ``bf16_autocast_active``, ``checkpoint``, ``log``,
        ``dataset_fingerprint``.

    Under ``torchrun`` (an initialised process group of W > 1 ranks) every rank calls
    this with the same arguments: each trains on ``batch_scenes / W`` scenes of every
    step's global batch, gradients are averaged, and only rank 0 writes ``out_dir`` and
    evaluates; all ranks return the same summary.

    Raises:
        TrainingDiverged: a NaN/Inf loss or gradient (names the step; the checkpoint on
            disk stays the last good one).
        ValueError: under torchrun, ``batch_scenes`` not divisible by the world size.
        CheckpointError: resuming from a corrupt checkpoint or a mismatching run.
        svorf.data.DatasetError: an invalid data folder.
    """
    out = Path(out_dir)
    ckpt_path = out / CHECKPOINT_NAME
    if ckpt_path.exists() and not resume:
        raise CheckpointError(
            f"{ckpt_path}: the run folder already holds a checkpoint; pass resume=True "
            f"(--resume) or choose another output folder"
        )
    device = resolve_device(train_cfg.device)
    dctx = distributed.current()
    main = dctx is None or dctx.is_main  # the process that writes files and logs
    lo, hi = 0, train_cfg.batch_scenes  # this process's rows of each global batch
    if dctx is not None:
        b = distributed.local_batch(train_cfg.batch_scenes, dctx.world_size)
        lo, hi = dctx.rank * b, (dctx.rank + 1) * b
        device = distributed.local_device(dctx, device)
    # truth=False: the ids and depth files are not even read (unsupervised training).
    dataset = MultiViewDataset(
        data_dir, image_size=model_cfg.image_size, max_scenes=max_scenes, truth=False
    )
    eval_ds = None
    if main and eval_data is not None and train_cfg.eval_every:
        eval_ds = MultiViewDataset(
            eval_data, image_size=model_cfg.image_size, max_scenes=train_cfg.eval_scenes
        )
    sampler = RaySampler(
        dataset, train_cfg.rays_per_scene, nvs=model_cfg.nvs, ray_sampling=train_cfg.ray_sampling
    )
    sampler_warm = sampler
    if train_cfg.nvs_warmup and model_cfg.nvs:
        sampler_warm = RaySampler(
            dataset,
            train_cfg.rays_per_scene,
            nvs=False,
            ray_sampling=train_cfg.ray_sampling,
            error_map=sampler.error_map,
        )
    error_map = sampler.error_map  # "error_driven": fed with every step's per-ray errors
    if error_map is not None and dctx is not None:
        raise ValueError(
            f"ray_sampling={train_cfg.ray_sampling!r} keeps per-process error maps and is not "
            f"supported under torchrun; use 'object_heavy' or 'uniform' there"
        )
    data_info = {
        "fingerprint": dataset.fingerprint,
        "root": str(Path(data_dir).resolve()),
        "n_scenes": len(dataset),
        "image_hw": list(dataset.image_hw),
        "preset": dataset.preset,
    }

    torch.manual_seed(train_cfg.seed)
    gen = torch.Generator().manual_seed(train_cfg.seed)
    model = SVORF(model_cfg).to(device)
    if dctx is not None:
        model = distributed.prepare_model(model, device, dctx)
    opt = torch.optim.Adam(model.parameters(), lr=lr_at(train_cfg, 0), betas=train_cfg.betas)
    start, wall_offset, resumed_loss = 0, 0.0, math.nan
    init_info: dict[str, Any] | None = None
    out.mkdir(parents=True, exist_ok=True)
    log_path, eval_path = out / "log.jsonl", out / "eval.jsonl"

    if resume and ckpt_path.exists():
        ckpt = read_checkpoint(ckpt_path)
        # Through from_dict: a checkpoint written before a config field existed holds the
        # field's default (the behaviour it was trained with), not a mismatch.
        saved = ModelConfig.from_dict(dict(ckpt["model_config"])).to_dict()
        if saved != model_cfg.to_dict():
            diff = sorted(k for k, v in model_cfg.to_dict().items() if saved.get(k) != v)
            raise CheckpointError(
                f"{ckpt_path}: resume with a different model config (fields {diff})"
            )
        old = TrainConfig.from_dict(dict(ckpt["train_config"])).to_dict()  # new fields: defaults
        diff = sorted(
            k
            for k, v in train_cfg.to_dict().items()
            if k not in _RESUMABLE_CHANGES and old.get(k) != v
        )
        if diff:
            raise CheckpointError(
                f"{ckpt_path}: resume with a different train config (fields {diff})"
            )
        fp = ckpt.get("dataset", {}).get("fingerprint")
        if fp != dataset.fingerprint:
            raise CheckpointError(
                f"{ckpt_path}: the data in {data_dir} differs from the run's training data "
                f"(fingerprint {str(fp)[:12]} vs {dataset.fingerprint[:12]})"
            )
        try:
            model.load_state_dict(ckpt["model"])
            opt.load_state_dict(ckpt["optimizer"])
            _set_rng_state(ckpt["rng"], gen, device)
            if error_map is not None and "error_map" in ckpt:
                error_map.load_state_dict(ckpt["error_map"])
        except (RuntimeError, ValueError, KeyError, TypeError) as e:
            raise CheckpointError(
                f"{ckpt_path}: cannot restore the checkpoint ({_first_line(e)[:160]})"
            ) from e
        start, wall_offset = int(ckpt["step"]), float(ckpt.get("wall_s", 0.0))
        resumed_loss = float(ckpt.get("loss", math.nan))
        init_info = ckpt.get("init_from")
        # The state now lives in model/optimizer; the checkpoint's own copy of the weights
        # would otherwise stay alive (a second copy of the model) for the whole run.
        del ckpt
        if main:
            _truncate_jsonl(log_path, start)
            _truncate_jsonl(eval_path, start)
    elif main:
        for p in (log_path, eval_path):
            p.unlink(missing_ok=True)
    if init_from is not None and start == 0:
        init_info = init_weights_from(getattr(model, "module", model), init_from)
    if dctx is not None:  # identical already (same seed / checkpoint); made certain here
        distributed.broadcast_module(model)
    if main:
        atomic_write_json(
            out / "config.json",
            {
                "model": model_cfg.to_dict(),
                "train": train_cfg.to_dict(),
                "dataset": data_info,
                **({"init_from": init_info} if init_info else {}),
            },
        )

    def save(step: int, wall: float) -> None:
        _atomic_torch_save(
            {
                "format": CHECKPOINT_FORMAT,
                "step": step,
                "model": model.state_dict(),
                "optimizer": opt.state_dict(),
                "rng": _rng_state(gen, device),
                "model_config": model_cfg.to_dict(),
                "train_config": train_cfg.to_dict(),
                "dataset": data_info,
                "wall_s": wall,
                "loss": last_loss,
                "torch_version": str(torch.__version__),
                **({"error_map": error_map.state_dict()} if error_map is not None else {}),
                **({"init_from": init_info} if init_info else {}),
            },
            ckpt_path,
        )

    def run_eval(step: int, wall: float) -> None:
        assert eval_ds is not None
        fn = eval_fn or (lambda m, d: default_eval(m, d, train_cfg.eval_scenes))
        model.eval()
        try:
            forked = [device] if device.type == "cuda" else []
            with torch.random.fork_rng(devices=forked), torch.no_grad():
                metrics = fn(model, eval_ds)
        finally:
            model.train()
        _append_jsonl(
            eval_path,
            {"step": step, "wall_s": round(wall, 3), **{k: float(v) for k, v in metrics.items()}},
        )

    saved: int | None = start if ckpt_path.exists() else None

    def _kept(step: int | None) -> str:
        if step is None:
            return "no checkpoint was written yet"
        return f"{ckpt_path} keeps the last good state (step {step})"

    bar = None
    if progress and main:
        from tqdm import tqdm

        bar = tqdm(
            total=train_cfg.steps,
            initial=start,
            desc="svorf train",
            unit="step",
            dynamic_ncols=True,
        )
    model.train()
    t0 = time.perf_counter()
    paused = 0.0  # seconds spent in eval / checkpoint writing, kept out of wall_s
    last_loss = resumed_loss
    last_log_t, last_log_step = t0, start
    params = [p for p in model.parameters() if p.requires_grad]
    rand_ctx = (
        (lambda: nullcontext())
        if dctx is None
        else (lambda: distributed.GlobalBatchRandom(dctx.rank, dctx.world_size, hi - lo))
    )
    try:
        for step in range(start, train_cfg.steps):
            progress = step / train_cfg.steps
            if max_wall_s is not None:
                now_wall = wall_offset + time.perf_counter() - t0 - paused
                progress = max(progress, now_wall / max_wall_s if max_wall_s > 0 else 1.0)
            lr = lr_at(train_cfg, step, progress)
            for group in opt.param_groups:
                group["lr"] = lr
            smp = sampler_warm if step < train_cfg.nvs_warmup else sampler
            # Under torchrun every rank draws the whole global batch (the same draws as
            # one process) and keeps its rows.
            batch = smp.sample(smp.sample_scenes(train_cfg.batch_scenes, gen), gen)
            if dctx is not None:
                batch = _batch_rows(batch, lo, hi)
            batch = batch.to(device)
            with rand_ctx():
                # In train mode the model draws the packed-11 slot mask itself (global RNG).
                out_r = model(
                    batch.images,
                    batch.rays_o,
                    batch.rays_d,
                    perturb=True,
                    input_c2w=batch.input_c2w,
                )
                loss, parts = model.loss(out_r, batch.target_rgb)
            if error_map is not None:
                error_map.update(
                    batch.scenes,
                    batch.target_view,
                    batch.target_pixel,
                    (out_r.rgb.detach() - batch.target_rgb).pow(2).mean(-1),
                )
            done = step + 1
            if dctx is not None:
                opt.zero_grad(set_to_none=True)
                loss.backward()
                loss, parts = _average_step(params, loss, parts, dctx.world_size)
            if not torch.isfinite(loss):
                shown = ", ".join(f"{k}={float(v):.4g}" for k, v in parts.items())
                raise TrainingDiverged(
                    f"non-finite loss {float(loss.detach())} at step {done} ({shown}); "
                    f"{_kept(saved)}"
                )
            if dctx is None:
                opt.zero_grad(set_to_none=True)
                loss.backward()
            gnorm = torch.nn.utils.clip_grad_norm_(model.parameters(), float("inf"))
            if not torch.isfinite(gnorm):
                raise TrainingDiverged(
                    f"non-finite gradient norm at step {done} (loss {float(loss.detach()):.6g}); "
                    f"{_kept(saved)}"
                )
            opt.step()
            last_loss = float(loss.detach())
            if bar is not None:
                bar.update(1)
                bar.set_postfix(loss=f"{last_loss:.5f}")
            now = time.perf_counter()
            wall = wall_offset + now - t0 - paused
            if dctx is not None and max_wall_s is not None:  # all ranks stop at one step
                wall = distributed.all_reduce_max(wall, device)
            out_of_time = max_wall_s is not None and wall >= max_wall_s
            if main and (done % train_cfg.log_every == 0 or done == train_cfg.steps or out_of_time):
                sps = (done - last_log_step) / max(now - last_log_t, 1e-9)
                _append_jsonl(
                    log_path,
                    {
                        "step": done,
                        "wall_s": round(wall, 3),
                        "lr": lr,
                        "loss": last_loss,
                        "parts": {k: float(v) for k, v in parts.items()},
                        "steps_per_s": round(sps, 4),
                        "grad_norm": float(gnorm),
                    },
                )
                last_log_t, last_log_step = now, done
            tp = time.perf_counter()
            if eval_ds is not None and done % train_cfg.eval_every == 0:
                run_eval(done, wall)
            if done % train_cfg.ckpt_every == 0 or done == train_cfg.steps or out_of_time:
                if main:
                    save(done, wall)
                saved = done
            paused += time.perf_counter() - tp
            if out_of_time:
                break
    finally:
        if bar is not None:
            bar.close()
    elapsed = time.perf_counter() - t0
    end = saved if saved is not None else start
    steps_run = max(end - start, 0)
    summary = {
        "steps": end,
        "start_step": start,
        "final_loss": last_loss,
        "wall_s": round(elapsed, 3),
        "train_wall_s": round(wall_offset + elapsed - paused, 3),
        "s_per_step": round((elapsed - paused) / steps_run, 5) if steps_run else math.nan,
        "peak_rss_mb": round(_peak_rss_mb(), 1),
        "params": model.count_parameters(),
        "device": str(device),
        # What bf16_autocast resolved to on this device ("auto": native bf16 only).
        "bf16_autocast_active": bf16_autocast_on(model_cfg.bf16_autocast, device),
        "checkpoint": str(ckpt_path),
        "log": str(log_path),
        "dataset_fingerprint": dataset.fingerprint,
        "init_from": init_info,
    }
    if dctx is not None:
        summary["world_size"] = dctx.world_size
    if main:
        atomic_write_json(out / "summary.json", summary)
    return summary


def init_weights_from(model: torch.nn.Module, source: str | os.PathLike) -> dict[str, Any]:
    """Copy into ``model`` every tensor of the checkpoint ``source`` (a run folder or a
    checkpoint file) whose name and shape match; the rest keep their initialisation.

    A model with another slot count (Room-Diverse K=5 from a CLEVR-567 K=8 model) keeps its
    own slot embeddings; encoder, decoder, hypernetwork and composition carry over.

    Returns:
        ``{"path", "step", "loaded", "kept", "kept_names"}``: what was copied and what not.

    Raises:
        CheckpointError: ``source`` holds no readable checkpoint, or no tensor matched.
    """
    path = Path(source)
    if path.is_dir():
        path = path / CHECKPOINT_NAME
    if not path.is_file():
        raise CheckpointError(f"--init-from {source}: no checkpoint at {path}")
    ckpt = read_checkpoint(path)
    theirs = ckpt["model"]
    own = model.state_dict()
    take = {k: v for k, v in theirs.items() if k in own and own[k].shape == v.shape}
    if not take:
        raise CheckpointError(f"--init-from {source}: no tensor matches this model's")
    model.load_state_dict(take, strict=False)
    kept = sorted(k for k in own if k not in take)
    return {
        "path": str(path.resolve()),
        "step": int(ckpt.get("step", 0)),
        "loaded": len(take),
        "kept": len(kept),
        "kept_names": kept[:50],
    }


def _average_step(
    params: list[torch.nn.Parameter], loss: Tensor, parts: dict[str, Tensor], world_size: int
) -> tuple[Tensor, dict[str, Tensor]]:
    """All-reduce one step: mean gradients, mean loss and loss parts over the ranks.

    The per-rank losses are means over equal per-rank batches, so the mean gradient is
    the gradient of the global-batch loss. A NaN on any rank makes the mean NaN, so all
    ranks see the same loss and stop at the same step.
    """
    names = list(parts)
    stats = torch.stack([loss.detach().float(), *(parts[k].detach().float() for k in names)])
    mean = distributed.average_gradients(params, stats, world_size)
    out = {k: mean[i + 1] for i, k in enumerate(names)}
    if "psnr" in out and "mse" in out:  # PSNR of the global MSE, not a mean of PSNRs
        out["psnr"] = -10.0 * torch.log10(out["mse"].clamp_min(1e-10))
    return mean[0], out
