"""The one place where the benchmark touches the sVORF model package.

Where this sits: protocols never import ``svorf`` directly; they call the
functions here, so a change in svorf's API is absorbed in one file. What the
benchmark needs from svorf:

- configs: :func:`model_config` (scale, preset, ablation variant) and
  :func:`train_config` (scale, preset, seed, steps), both as frozen dataclasses
  plus :func:`config_dict` to store them as JSON; both start from
  :func:`base_configs`, the one place that picks svorf's configs per scale
  (the ``cpu`` scale trains the CLEVR-567 family and Room-Chair with the cpu recipe,
  docs/notes/cpu_recipe.md), and :func:`config_key` / :func:`learning_fields`, svorf's
  name for what a model learns (the same key ``svorf config`` prints);
- training: :func:`train` (resumable, into a run folder, optionally with a
  wall-clock budget) and :func:`load_model`;
- evaluation: :func:`open_dataset`, :func:`ground_truth`, :func:`predict_scene`
  (optionally with another scene's slots, ``slots_scene``, and only the input view);
- data helpers: :func:`dataset_fingerprint`, :func:`write_synthetic_split`;
- numerics (the ``stability`` protocol): :func:`volume_render`, :func:`slot_masks`,
  :func:`compose`, :func:`compose_density_weighted`, :func:`connectivity_loss`, and
  :func:`diverging_run` (a training run with a learning rate meant to blow up).

Ablation variants (paper tables ``tab:ablation`` and ``tab:supp_ablation``; the
packed-CLEVR-11 setting of ``tab:ab_num``) are ``ModelConfig`` field overrides in
:data:`VARIANTS`.
"""

from __future__ import annotations

import dataclasses
import json
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

__all__ = [
    "ADAPTER_VERSION",
    "RECIPE_CONFIG_SOURCE",
    "REFINE_LR_UNRECORDED",
    "VARIANTS",
    "VARIANT_LABELS",
    "Prediction",
    "SceneTruth",
    "base_configs",
    "compose",
    "compose_density_weighted",
    "config_dict",
    "config_key",
    "config_source",
    "connectivity_loss",
    "dataset_fingerprint",
    "default_refine_lr",
    "diverging_run",
    "ground_truth",
    "init_preset",
    "learning_fields",
    "load_model",
    "model_config",
    "num_slots",
    "open_dataset",
    "predict_scene",
    "refinement_of",
    "slot_masks",
    "svorf_preset",
    "train",
    "train_config",
    "variant_adjustments",
    "volume_render",
    "write_synthetic_split",
]

#: The slots' Adam learning rate of test-time refinement in reports that record
#: ``refine_slots`` but no ``refine_lr``: every ``--refine-slots`` report written before the
#: rate became an option (2026-12-05) refined at this rate.
REFINE_LR_UNRECORDED = 3e-3


def default_refine_lr() -> float:
    """The slots' Adam learning rate of test-time refinement when none is given
    (``svorf.refine.REFINE_LR``)."""
    from svorf.refine import REFINE_LR

    return float(REFINE_LR)


def refinement_of(settings: dict[str, Any]) -> tuple[int, float | None]:
    """``(steps, learning rate)`` of the test-time refinement a report's ``scale_settings``
    record: ``(0, None)`` for the encoder's slots; a report without ``refine_lr`` refined at
    :data:`REFINE_LR_UNRECORDED`."""
    steps = int(settings.get("refine_slots") or 0)
    if not steps:
        return 0, None
    lr = settings.get("refine_lr")
    return steps, REFINE_LR_UNRECORDED if lr is None else float(lr)


#: Bumped when anything here changes what a trained run or an evaluation means
#: (it is part of the model cache key and of the evaluation cache key).
ADAPTER_VERSION = "1"

#: Ablation / setting variants as ModelConfig overrides.
VARIANTS: dict[str, dict[str, Any]] = {
    "full": {},
    "wo_nvs": {"nvs": False},
    "wo_cr": {"connectivity": False},
    "density_weighted": {"composition": "density_weighted"},
    "wo_sa": {"self_attention": False},
    "wo_hypernetwork": {"hypernetwork": False},
    "slot_attention": {"slot_module": "slot_attention"},
    "slot_mixer": {"composition": "slot_mixer"},
    # Paper 4.6 "Spatial Arrangements": svorf's packed-clevr11 preset (:func:`svorf_preset`)
    # gives the 11 slots and the 4 masked off per training step, or none masked where the
    # scale's recipe says so (the cpu recipe).
    "packed11": {},
}

VARIANT_LABELS: dict[str, str] = {
    "full": "sVORF (ours)",
    "wo_nvs": "sVORF (w/o NVS)",
    "wo_cr": "sVORF (w/o CR)",
    "density_weighted": "sVORF (density-weighted)",
    "wo_sa": "sVORF (w/o SA)",
    "wo_hypernetwork": "sVORF (w/o Hypernetwork)",
    "slot_attention": "sVORF (w Slot-Attention)",
    "slot_mixer": "sVORF (w SM)",
    "packed11": "sVORF (11 slots)",
}


def _svorf_config():
    from svorf import config

    return config


def _svorf_train():
    try:
        from svorf import train as svorf_train
    except ImportError as err:  # pragma: no cover - depends on the svorf checkout
        raise ImportError(
            f"benchmark needs svorf.train (train, train_config, load_run, predict_scene): {err}"
        ) from err
    return svorf_train


def init_preset(train_preset: str) -> str | None:
    """The training preset whose model starts ``train_preset``'s (svorf's
    ``PresetSpec.init_from``; the paper starts Room-Diverse from CLEVR-567), else None."""
    spec = _svorf_train().PRESETS.get(train_preset)
    return None if spec is None else spec.init_from


def svorf_preset(train_preset: str, variant: str) -> str:
    """svorf's training-preset name for a benchmark model (``svorf.train.PRESETS``).

    The packed-CLEVR-11 setting trains on CLEVR-567 data under svorf's
    ``packed-clevr11`` preset (11 slots, 4 masked per step; none at the cpu scale).
    """
    return "packed-clevr11" if variant == "packed11" else train_preset


def num_slots(scale: str, train_preset: str, variant: str = "full") -> int:
    """K (background included) that svorf's registry gives this model at ``scale``: the
    preset's, or the scale's recipe's own for that preset (``svorf.registry.slots_for``)."""
    from svorf.registry import slots_for

    presets = _svorf_train().PRESETS
    key = svorf_preset(train_preset, variant)
    if key not in presets:
        raise ValueError(f"svorf has no training preset {key!r}; known: {sorted(presets)}")
    return slots_for(scale, key)


RECIPE_CONFIG_SOURCE = "svorf.train.run_configs (cpu recipe)"
SCALE_CONFIG_SOURCE = "svorf.train.run_configs"


def config_source(scale: str, train_preset: str, variant: str = "full") -> str:
    """Which svorf configs a model gets (see :func:`base_configs`): the scale's, with the
    cpu recipe where ``svorf.train.recipe_applies``."""
    key = svorf_preset(train_preset, variant)
    if _svorf_train().recipe_applies(scale, key):
        return RECIPE_CONFIG_SOURCE
    return SCALE_CONFIG_SOURCE


def base_configs(
    scale: str, train_preset: str, variant: str = "full", image_size: int | None = None
) -> tuple[Any, Any]:
    """svorf's (ModelConfig, TrainConfig) for a benchmark model, before ablation overrides:
    ``svorf.train.run_configs(scale, preset)``, the same configs ``svorf train --scale S
    --preset P`` uses (the cpu recipe at ``cpu`` for its presets).

    Raises:
        ValueError: on an unknown scale or preset (svorf's message).
    """
    key = svorf_preset(train_preset, variant)
    return _svorf_train().run_configs(scale, key, image_size=image_size)


def model_config(
    scale: str, train_preset: str, variant: str = "full", image_size: int | None = None
) -> Any:
    """The svorf ``ModelConfig`` of one benchmark model.

    Args:
        scale: ``smoke`` / ``cpu`` / ``paper`` (see :func:`base_configs`).
        train_preset: the dataset preset the model trains on (sets K via
            ``svorf.train.PRESETS``: 8 for CLEVR-567, 5 for the Room datasets).
        variant: a key of :data:`VARIANTS` (ablation switches, packed-11 setting),
            applied on top of the base config.
        image_size: encoder input side; None = svorf's default for the scale.

    Raises:
        ValueError: on an unknown variant or preset.
    """
    if variant not in VARIANTS:
        raise ValueError(f"unknown model variant {variant!r}; known: {sorted(VARIANTS)}")
    mcfg, _ = base_configs(scale, train_preset, variant, image_size=image_size)
    overrides = dict(VARIANTS[variant])
    overrides.update(variant_adjustments(mcfg, variant)[0])
    return dataclasses.replace(mcfg, **overrides) if overrides else mcfg


def variant_adjustments(base_cfg: Any, variant: str) -> tuple[dict[str, Any], list[str]]:
    """Fields of the base config that an ablation variant cannot keep, and why.

    The cpu recipe's slot-centred locality multiplies each slot's *density* by an envelope
    around the slot's centre; Slot-Mixer composition has no per-slot density to localise, so
    its row drops ``slot_locality`` (and the centres it needs). Returns ``(field overrides,
    notes)``; both empty when the variant combines with the base config as it is.
    """
    changes: dict[str, Any] = {}
    notes: list[str] = []
    comp = VARIANTS.get(variant, {}).get("composition")
    if comp == "slot_mixer" and getattr(base_cfg, "slot_locality", None) is not None:
        changes.update(slot_locality=None, slot_centre="learned")
        narrow = getattr(base_cfg, "slot_locality_narrow", None)
        if narrow is not None:  # the radius schedule goes with the radius
            changes["slot_locality_narrow"] = None
        if getattr(base_cfg, "slot_locality_xy", False):  # and so does its shape
            changes["slot_locality_xy"] = False
        notes.append(
            f"{variant}: Slot-Mixer composition has no per-slot density to localise, so the "
            f"base config's slot_locality={base_cfg.slot_locality} and "
            f"slot_centre={base_cfg.slot_centre!r}"
            + (f" (narrowed by slot_locality_narrow={narrow})" if narrow is not None else "")
            + (
                " (a cylinder, slot_locality_xy)"
                if changes.get("slot_locality_xy") is False
                else ""
            )
            + " are off for this model (slot_locality=None)."
        )
    return changes, notes


def train_config(
    scale: str, train_preset: str, variant: str, seed: int, device: str, steps: int | None = None
) -> Any:
    """svorf's ``TrainConfig`` for the model, with the benchmark's seed, device (and steps)."""
    changes: dict[str, Any] = {"seed": int(seed), "device": device}
    if steps is not None:
        changes["steps"] = int(steps)
    _, tcfg = base_configs(scale, train_preset, variant)
    return dataclasses.replace(tcfg, **changes)


def config_key(model_cfg: Any, train_cfg: Any) -> str:
    """svorf's config key of a model (``svorf.train_config.config_key``): what ``svorf config``
    prints for the same configs; device and logging settings do not change it."""
    return _svorf_train().config_key(model_cfg, train_cfg)


def learning_fields(train_cfg: Any) -> dict[str, Any]:
    """The TrainConfig fields that change what a run learns, as a dict (svorf's
    ``learning_fields``: every field but device, logging, checkpoint and evaluation cadence)."""
    return _svorf_train().learning_fields(train_cfg)


def config_dict(cfg: Any) -> dict[str, Any]:
    """A frozen config dataclass as a plain JSON-able dict."""
    if hasattr(cfg, "to_dict"):
        return cfg.to_dict()
    d = dataclasses.asdict(cfg)
    return {k: list(v) if isinstance(v, tuple) else v for k, v in d.items()}


def train(
    data_dir: str | os.PathLike,
    run_dir: str | os.PathLike,
    model_cfg: Any,
    train_cfg: Any,
    *,
    progress: bool = True,
    max_wall_s: float | None = None,
    init_from: str | os.PathLike | None = None,
) -> dict[str, Any]:
    """Train (or resume training) one model into ``run_dir`` (svorf checkpoints there).

    Args:
        max_wall_s: training wall-time budget in seconds, summed over resumed calls
            (svorf's ``train(max_wall_s=)``: evaluation and checkpoint writing are not
            counted); the run stops at the budget or at ``train_cfg.steps``, whichever
            comes first. None = steps only.

    Returns:
        svorf's run summary (``TrainSummary.to_dict()``: steps, train_wall_s, final_loss,
        wall_s, s_per_step, peak_rss_mb, params, device...), JSON-able (non-finite floats
        become None).
    """
    st = _svorf_train()
    out = st.train(
        Path(data_dir),
        Path(run_dir),
        model_cfg,
        train_cfg,
        resume=True,
        progress=progress,
        max_wall_s=max_wall_s,
        init_from=init_from,
    )
    return _jsonable_summary(out.to_dict())


def _jsonable_summary(out: dict[str, Any]) -> dict[str, Any]:
    keep = {}
    for k, v in out.items():
        if isinstance(v, (bool, int, str)) or v is None:
            keep[k] = v
        elif isinstance(v, float):
            keep[k] = v if np.isfinite(v) else None
        elif k == "init_from" and isinstance(v, dict):  # what started the run (JSON already)
            keep[k] = json.loads(json.dumps(v))
    return keep


def load_model(run_dir: str | os.PathLike, device: str = "cpu") -> Any:
    """The trained model of ``run_dir`` in eval mode on ``device``."""
    model, _info = _svorf_train().load_run(Path(run_dir), device=device)
    model.eval()
    return model


def open_dataset(root: str | os.PathLike, image_size: int | None = None) -> Any:
    """svorf's in-memory ``MultiViewDataset`` of a split folder."""
    from svorf.data import MultiViewDataset

    return MultiViewDataset(root, image_size=image_size)


@dataclass(frozen=True)
class SceneTruth:
    """Ground truth of one test scene (CPU tensors).

    Attributes:
        images: float32 [V, 3, H, W] in [0, 1].
        instances: int64 [V, H, W], 0 = background.
        depth_z: float32 [V, H, W] planar depth (world units), inf/nan = none.
    """

    images: torch.Tensor
    instances: torch.Tensor
    depth_z: torch.Tensor


def ground_truth(dataset: Any, index: int) -> SceneTruth:
    """Ground truth of the scene at position ``index`` of ``dataset``."""
    sv = dataset[index]
    return SceneTruth(images=sv.images, instances=sv.instances.long(), depth_z=sv.depth_z.float())


@dataclass(frozen=True)
class Prediction:
    """What the model renders for one scene from its input view (CPU tensors).

    V is the scene's view count, or 1 (the input view) for
    ``predict_scene(..., input_view_only=True)``.

    Attributes:
        rgb: float32 [V, 3, H, W] in [0, 1] (the input view's is the reconstruction).
        depth_z: float32 [V, H, W] rendered planar depth, world units.
        labels: int64 [V, H, W] arg-max slot per pixel.
    """

    rgb: torch.Tensor
    depth_z: torch.Tensor
    labels: torch.Tensor


class _InputViewOnly:
    """``dataset`` with one view per scene (``view``), so svorf renders only that view.

    Every per-view tensor of svorf's ``SceneViews`` (leading dim V) is sliced to
    ``[view : view + 1]``; ``n_views`` is 1. Only what ``svorf.train.predict_scene``
    reads is offered (``len``, ``[i]``, ``n_views``, ``image_hw``): anything else
    fails loudly instead of silently seeing every view.
    """

    def __init__(self, dataset: Any, view: int) -> None:
        self._dataset = dataset
        self._view = int(view)
        self.n_views = 1
        self.image_hw = dataset.image_hw

    def __len__(self) -> int:
        return len(self._dataset)

    def __getitem__(self, i: int) -> Any:
        sv = self._dataset[i]
        v = self._view
        return dataclasses.replace(
            sv,
            **{
                f.name: getattr(sv, f.name)[v : v + 1]
                for f in dataclasses.fields(sv)
                if isinstance(getattr(sv, f.name), torch.Tensor)
            },
        )


def predict_scene(
    model: Any,
    dataset: Any,
    index: int,
    input_view: int = 0,
    *,
    slots_scene: int | None = None,
    input_view_only: bool = False,
    refine_steps: int = 0,
    refine_lr: float | None = None,
) -> Prediction:
    """Render the views of scene ``index`` from ``input_view`` with ``model``.

    Args:
        model: from :func:`load_model`.
        dataset: from :func:`open_dataset`.
        index: scene position in ``dataset``.
        input_view: the view the model encodes.
        slots_scene: if given, the slots are encoded from this scene's ``input_view``
            instead and placed in scene ``index``'s input-camera frame (svorf's
            ``predict_scene(slots_scene=)``): the scene-shuffle control of
            :func:`benchmark.evaluate.evaluate_model`. ``slots_scene == index`` is the
            same as None.
        input_view_only: render only ``input_view``; the returned tensors then have
            ``V = 1`` (the input view) instead of every view of the scene.
        refine_steps: if > 0, the slots are refined this many steps on the pixels of the
            view they were encoded from before rendering (svorf's test-time slot
            refinement, ``svorf.refine``); 0 = the encoder's slots.
        refine_lr: the slots' Adam learning rate of that refinement (None:
            :func:`default_refine_lr`).

    Returns:
        The :class:`Prediction` (every view, or only the input view).

    Raises:
        ValueError: ``index``, ``input_view`` or ``slots_scene`` out of range.
    """
    st = _svorf_train()
    n = len(dataset)
    if slots_scene is not None and not 0 <= int(slots_scene) < n:
        raise ValueError(f"slots_scene must be a scene position in [0, {n}), got {slots_scene}")
    if not 0 <= int(input_view) < dataset.n_views:
        raise ValueError(f"input_view must be in [0, {dataset.n_views}), got {input_view}")
    kw: dict[str, Any] = {} if slots_scene is None else {"slots_scene": int(slots_scene)}
    if refine_steps:
        kw["refine_steps"] = int(refine_steps)
        if refine_lr is not None:
            kw["refine_lr"] = float(refine_lr)
    if input_view_only:
        dataset, input_view = _InputViewOnly(dataset, input_view), 0
    with torch.no_grad():
        out = st.predict_scene(model, dataset, index, input_view=input_view, **kw)
    rgb = out.rgb.detach().float().cpu().permute(0, 3, 1, 2)  # [V, H, W, 3] -> [V, 3, H, W]
    return Prediction(
        rgb=rgb.clamp(0.0, 1.0).contiguous(),
        depth_z=out.depth_z.detach().float().cpu(),
        labels=out.labels.detach().long().cpu(),
    )


def dataset_fingerprint(root: str | os.PathLike) -> str:
    """SHA-256 (hex) over a split's manifest and scene JSONs (``scenefmt``'s definition)."""
    from scenefmt import dataset_fingerprint as fp

    return fp(root)


def write_synthetic_split(root: str | os.PathLike, **kwargs: Any) -> Path:
    """svorf's analytic test-fixture writer (spheres on a plate, exact masks/depth)."""
    from svorf.synthetic import write_synthetic_split as write

    return write(root, **kwargs)


def volume_render(
    sigma: torch.Tensor, rgb: torch.Tensor, t: torch.Tensor, last_delta: float = 1e10
):
    """svorf's volume renderer: ``(rgb [...,3], depth [...], weights [...,N], acc [...])``."""
    from svorf.render import volume_render as vr

    return vr(sigma, rgb, t, last_delta=last_delta)


def slot_masks(logits: torch.Tensor, valid: torch.Tensor | None) -> torch.Tensor:
    """sVORF's slot masks m = masked softmax over the last (slot) axis, float32."""
    from svorf.compose import masked_softmax

    return masked_softmax(logits, valid, dim=-1)


def compose(sigma_k: torch.Tensor, rgb_k: torch.Tensor, m: torch.Tensor):
    """sVORF's composition: ``(sigma [B, P], rgb [B, P, 3])`` from [B, K, P] fields, m [B, P, K]."""
    from svorf.compose import compose as c

    return c(sigma_k, rgb_k, m)


def compose_density_weighted(
    sigma_k: torch.Tensor, rgb_k: torch.Tensor, valid: torch.Tensor | None = None
):
    """The uORF-style ablation: ``(sigma [B, P], rgb [B, P, 3], m [B, P, K])``."""
    from svorf.compose import compose_density_weighted as c

    return c(sigma_k, rgb_k, valid)


def connectivity_loss(sigma_k, t, far_r, near: float, far: float, slot_mask=None):
    """svorf's connectivity (per-slot distortion) loss, a float32 scalar."""
    from svorf.losses import connectivity_loss as c

    return c(sigma_k, t, far_r, near, far, slot_mask)


def diverging_run(
    workdir: str | os.PathLike, scale: str, lr: float, max_steps: int = 30, seed: int = 0
) -> dict[str, Any]:
    """Train the scale's model on a tiny synthetic split with learning rate ``lr`` and a
    checkpoint every step, until svorf's NaN guard stops it (or ``max_steps``).

    Returns:
        ``diverged`` (the guard raised), ``diverged_at_step`` (the step it named),
        ``message`` (its one line), ``checkpoint_step`` (the step of the checkpoint left
        on disk), ``checkpoint_loads`` (``load_run`` reads it), ``nonfinite_params``
        (NaN/Inf entries in its weights) and ``temp_files`` (leftover ``*.tmp*`` files).
    """
    st = _svorf_train()
    root = Path(workdir)
    split = write_synthetic_split(root / "train", n_scenes=4, resolution=32, seed=seed)
    mcfg, tcfg = st.run_configs(scale, "synthetic", image_size=32, device="cpu")
    tcfg = dataclasses.replace(
        tcfg, lr=float(lr), steps=int(max_steps), ckpt_every=1, seed=int(seed)
    )
    run = root / "run"
    out: dict[str, Any] = {"diverged": False, "diverged_at_step": None, "message": None}
    try:
        st.train(split, run, mcfg, tcfg, progress=False)
    except st.TrainingDiverged as e:
        out.update(diverged=True, message=str(e), diverged_at_step=e.step)
    try:
        model, info = st.load_run(run, device="cpu")
        out["checkpoint_loads"] = True
        out["checkpoint_step"] = int(info.step)
        out["nonfinite_params"] = int(
            sum((~torch.isfinite(p)).sum() for p in model.state_dict().values()
                if p.is_floating_point())
        )  # fmt: skip
    except (st.CheckpointError, OSError, RuntimeError, ValueError) as e:  # a failed row
        out.update(checkpoint_loads=False, checkpoint_step=None, nonfinite_params=None)
        out["load_error"] = f"{type(e).__name__}: {e}"
    out["temp_files"] = len([p for p in run.rglob("*") if ".tmp" in p.name])
    return out


def read_manip_truth(root: str | os.PathLike, scene: int, hw: Any = None) -> Any:
    """The moved / background-changed ground truth of a manipulation split's scene
    (``svorf.edit_scene.ManipTruth`` at resolution ``hw``, default the stored one)."""
    from svorf.edit_scene import read_manip_truth as read

    return read(root, scene, None if hw is None else tuple(hw))


def edit_scene(model: Any, dataset: Any, index: int, truth: Any, input_view: int = 0) -> Any:
    """Render scene ``index`` unedited, with ``truth``'s object moved (slot picked by IoU with
    its ``_mask_for_moving``, as uORF) and with the background of ``truth``'s providing view
    (``svorf.edit_scene.EditResult``). The move is left out when the object is not visible
    in the input view."""
    from svorf.edit_scene import edit_scene as edit

    target = truth.mask_for_moving[input_view]
    move = bool(target.any())
    return edit(
        model, dataset, index, input_view=input_view,
        target_mask=target if move else None, offset=truth.offset if move else None,
        donor_image=truth.providing[input_view],
    )  # fmt: skip
