"""Checkpoint I/O of training runs: the format, writing, checking, restoring and loading.

Where this sits: between ``svorf.train`` (the loop writes a checkpoint every
``ckpt_every`` steps and restores one on ``resume=True``) and everything that reads a
run folder (``load_run`` for ``svorf render``, the recipe and the benchmark adapter;
``init_weights_from`` for ``--init-from``). This module alone knows what a checkpoint
holds. Every name is re-exported by ``svorf.train``, the old home of these names.

``checkpoint.pt`` (format :data:`CHECKPOINT_FORMAT`) is a ``torch.save`` dict: ``format``,
``step``, ``model`` and ``optimizer`` state dicts, ``rng`` (global torch, CUDA and the data
generator's states), ``model_config`` / ``train_config`` as JSON dicts, ``dataset``
(fingerprint, root, scene count, image size, preset), ``wall_s``, ``max_wall_s`` (the
run's training-time budget, None for a run stopped by its steps alone), ``loss``,
``torch_version``, and when used ``error_map`` (the ``"error_driven"`` ray sampling's
state), ``init_from`` and ``model_ema`` (the moving average of ``TrainConfig.ema_decay``, a
state dict of the model). It is written atomically (temp file + ``os.replace``), so the
file on disk is always the last good state.
"""

from __future__ import annotations

import os
import re
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch

from scenefmt import default_file_mode, legacy_fingerprint
from svorf.config import PROGRESS_FIELDS as MODEL_PROGRESS_FIELDS
from svorf.config import ModelConfig
from svorf.model import SVORF
from svorf.optim import parse_probe
from svorf.ray_sampling import ErrorMap
from svorf.train_config import PROGRESS_FIELDS as TRAIN_PROGRESS_FIELDS
from svorf.train_config import TrainConfig

__all__ = [
    "CHECKPOINT_FORMAT",
    "CHECKPOINT_NAME",
    "RENDER_PROBE_FIELDS",
    "WEIGHTS",
    "CheckpointError",
    "RunInfo",
    "atomic_torch_save",
    "check_resumable",
    "check_resumable_budget",
    "init_weights_from",
    "load_run",
    "progress_schedules",
    "read_checkpoint",
    "render_probe",
    "restore_checkpoint",
    "rng_state",
    "set_rng_state",
    "write_checkpoint",
]

CHECKPOINT_NAME = "checkpoint.pt"
CHECKPOINT_FORMAT = "svorf-checkpoint-1"

#: Fields that ``SVORF`` reads at every render and that no sub-network keeps a copy of, so
#: a trained model can be rendered with another value (a probe, not a model: the weights
#: were trained under the checkpoint's value): the scene priors, the samples per ray
#: (the quadrature) and where they are taken (the box and its floor clip).
RENDER_PROBE_FIELDS = (
    "fg_zmin",
    "fg_box",
    "bg_outside_fg",
    "n_coarse",
    "n_fine",
    "comp_temperature",
    "clip_to_box",
    "box_z",
    "clip_floor_z",
    "clip_floor_front",
    "eval_mask_rule",
)

#: Fields that may differ between a checkpoint and the config that resumes it.
_RESUMABLE_CHANGES = {"steps", "log_every", "ckpt_every", "eval_every", "eval_scenes", "device"}


class CheckpointError(ValueError):
    """A run folder without a readable checkpoint; the message is one line."""


def atomic_torch_save(obj: Any, path: Path) -> None:
    """``torch.save(obj)`` to ``path`` atomically: a hidden temp file beside it (file mode
    as ``open()`` gives, not ``mkstemp``'s 0600), fsync, then ``os.replace``."""
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


def _first_line(e: BaseException) -> str:
    """The informative line of an exception message (torch's load errors are long)."""
    lines = [re.sub(r"\x1b\[[0-9;]*m", "", x).strip() for x in str(e).splitlines()]
    lines = [x for x in lines if x]
    for x in lines:
        if "error:" in x.lower():
            return x
    return lines[0] if lines else type(e).__name__


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


def rng_state(gen: torch.Generator, device: torch.device | None = None) -> dict[str, Any]:
    """The random states a checkpoint keeps: global torch, every CUDA device, the data
    generator ``gen``, and the generator of ``device`` when it is a CUDA device."""
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


def set_rng_state(
    state: dict[str, Any], gen: torch.Generator, device: torch.device | None = None
) -> None:
    """Restore the states of :func:`rng_state` (``cuda_device`` into ``device``)."""
    torch.set_rng_state(state["torch"])
    if state.get("cuda") and torch.cuda.is_available():
        torch.cuda.set_rng_state_all(state["cuda"])
    if device is not None and device.type == "cuda" and state.get("cuda_device") is not None:
        torch.cuda.set_rng_state(state["cuda_device"], device)
    gen.set_state(state["data"])


def write_checkpoint(
    path: Path,
    *,
    step: int,
    model: torch.nn.Module,
    optimizer: torch.optim.Optimizer,
    gen: torch.Generator,
    device: torch.device,
    model_cfg: ModelConfig,
    train_cfg: TrainConfig,
    dataset: dict[str, Any],
    wall_s: float,
    loss: float,
    max_wall_s: float | None = None,
    error_map: ErrorMap | None = None,
    init_from: dict[str, Any] | None = None,
    model_ema: dict[str, Any] | None = None,
    average_probes: dict[str, Any] | None = None,
) -> None:
    """Write the run's state after ``step`` optimizer steps to ``path`` (atomically).

    Args:
        model, optimizer: their state dicts are saved (a DDP-wrapped model as it is).
        gen: the data generator (its state and the global ones: :func:`rng_state`).
        dataset: ``fingerprint``, ``root``, ``n_scenes``, ``image_hw``, ``preset``.
        wall_s: the run's training wall time so far; loss: the last step's loss.
        max_wall_s: the run's training-time budget (None: its steps alone stop it).
        error_map: the ``"error_driven"`` ray sampling's state, when used.
        init_from: what :func:`init_weights_from` loaded at step 0, when used.
        model_ema: the averaged weights (a model state dict), when kept.
        average_probes: ``TrainConfig.average_probes``' averages
            (``ProbeAverages.state_dict``), when kept.
    """
    atomic_torch_save(
        {
            "format": CHECKPOINT_FORMAT,
            "step": step,
            "model": model.state_dict(),
            "optimizer": optimizer.state_dict(),
            "rng": rng_state(gen, device),
            "model_config": model_cfg.to_dict(),
            "train_config": train_cfg.to_dict(),
            "dataset": dataset,
            "wall_s": wall_s,
            "max_wall_s": max_wall_s,
            "loss": loss,
            "torch_version": str(torch.__version__),
            **({"error_map": error_map.state_dict()} if error_map is not None else {}),
            **({"init_from": init_from} if init_from else {}),
            **({"model_ema": model_ema} if model_ema is not None else {}),
            **({"model_average_probes": average_probes} if average_probes else {}),
        },
        path,
    )


def check_resumable(
    ckpt: dict[str, Any],
    path: Path,
    model_cfg: ModelConfig,
    train_cfg: TrainConfig,
    fingerprint: str,
    data_dir: str | os.PathLike,
    *,
    max_wall_s: float | None,
) -> None:
    """Refuse to resume the checkpoint ``ckpt`` (read from ``path``) with other configs
    or other data: the model config must be equal, the train config equal but for the
    bookkeeping fields (steps, logging, checkpoint and eval cadence, device), the
    training data's ``fingerprint`` the checkpoint's (or, for a checkpoint written before
    fingerprints rounded their numbers, the data's :func:`scenefmt.legacy_fingerprint`),
    and the training-time budget ``max_wall_s`` the checkpoint's where schedules follow
    the run's progress (:func:`check_resumable_budget`).

    Raises:
        CheckpointError: one line naming the fields that differ, or the data mismatch.
    """
    # Through from_dict: a checkpoint written before a config field existed holds the
    # field's default (the behaviour it was trained with), not a mismatch.
    saved = ModelConfig.from_dict(dict(ckpt["model_config"])).to_dict()
    if saved != model_cfg.to_dict():
        diff = sorted(k for k, v in model_cfg.to_dict().items() if saved.get(k) != v)
        raise CheckpointError(f"{path}: resume with a different model config (fields {diff})")
    old = TrainConfig.from_dict(dict(ckpt["train_config"])).to_dict()  # new fields: defaults
    diff = sorted(
        k for k, v in train_cfg.to_dict().items() if k not in _RESUMABLE_CHANGES and old.get(k) != v
    )
    if diff:
        raise CheckpointError(f"{path}: resume with a different train config (fields {diff})")
    fp = ckpt.get("dataset", {}).get("fingerprint")
    if fp != fingerprint and fp != legacy_fingerprint(data_dir):  # written before 2026-11-27
        raise CheckpointError(
            f"{path}: the data in {data_dir} differs from the run's training data "
            f"(fingerprint {str(fp)[:12]} vs {fingerprint[:12]})"
        )
    check_resumable_budget(ckpt, path, model_cfg, train_cfg, max_wall_s)


def progress_schedules(model_cfg: ModelConfig, train_cfg: TrainConfig) -> list[str]:
    """The config fields set in ``model_cfg`` / ``train_cfg`` whose effect follows the
    run's progress (its step over ``steps``, or its training time over the budget)."""
    model, train = model_cfg.to_dict(), train_cfg.to_dict()
    fields = [k for k in MODEL_PROGRESS_FIELDS if model.get(k) is not None]
    fields += [k for k in TRAIN_PROGRESS_FIELDS if train.get(k) is not None]
    if train.get("lr_decay", "none") != "none":
        fields.append("lr_decay")
    return fields


def _budget_words(max_wall_s: float | None) -> str:
    return "no time budget" if max_wall_s is None else f"a {max_wall_s:g} s budget"


def check_resumable_budget(
    ckpt: dict[str, Any],
    path: Path,
    model_cfg: ModelConfig,
    train_cfg: TrainConfig,
    max_wall_s: float | None,
) -> None:
    """Refuse to resume ``ckpt`` under another training-time budget than it was trained
    with when the configs hold schedules that follow the run's progress: the budget is
    the progress's denominator, so the schedules would jump back and run again (a
    finished 60-minute run resumed under 120 minutes would replay its second half). A
    checkpoint written before budgets were recorded is not checked.

    Raises:
        CheckpointError: one line naming both budgets, the schedules and the way out.
    """
    if "max_wall_s" not in ckpt:
        return
    old = ckpt["max_wall_s"]
    old = None if old is None else float(old)
    if old == max_wall_s:
        return
    fields = progress_schedules(model_cfg, train_cfg)
    if fields:
        raise CheckpointError(
            f"{path}: trained under {_budget_words(old)}, resumed under "
            f"{_budget_words(max_wall_s)}; its schedules that follow the run's progress "
            f"({', '.join(fields)}) would start again. Resume with the budget it was "
            "trained with, or start a new run from its weights (init_from)"
        )


def restore_checkpoint(
    ckpt: dict[str, Any],
    path: Path,
    model: torch.nn.Module,
    optimizer: torch.optim.Optimizer,
    gen: torch.Generator,
    device: torch.device,
    error_map: ErrorMap | None = None,
) -> None:
    """Load the model, optimizer, random states and error map of ``ckpt`` (read from
    ``path``) into the objects of a resumed run.

    Raises:
        CheckpointError: a state does not fit (one line).
    """
    try:
        model.load_state_dict(ckpt["model"])
        optimizer.load_state_dict(ckpt["optimizer"])
        set_rng_state(ckpt["rng"], gen, device)
        if error_map is not None and "error_map" in ckpt:
            error_map.load_state_dict(ckpt["error_map"])
    except (RuntimeError, ValueError, KeyError, TypeError) as e:
        raise CheckpointError(
            f"{path}: cannot restore the checkpoint ({_first_line(e)[:160]})"
        ) from e


@dataclass(frozen=True)
class RunInfo:
    """What a checkpoint says about its run (returned by :func:`load_run`)."""

    model: ModelConfig
    train: TrainConfig
    step: int
    dataset: dict[str, Any]
    """``fingerprint``, ``root``, ``n_scenes``, ``image_hw`` of the training data."""
    wall_s: float
    weights: str = "raw"
    """Which weights the model holds: "raw" (the optimizer's), "ema" (their average) or
    the name of one of ``TrainConfig.average_probes``."""


#: ``load_run``'s choices of weights: the average when the run kept one ("auto"), the
#: optimizer's weights ("raw"), or the average, required ("ema"). A run trained with
#: ``TrainConfig.average_probes`` also takes each probe's name ("ema0.9995", "tail0.8").
WEIGHTS = ("auto", "raw", "ema")


def load_run(
    run_dir: str | os.PathLike, device: str | torch.device = "cpu", weights: str = "auto"
) -> tuple[SVORF, RunInfo]:
    """Load the latest checkpoint of a run folder.

    Args:
        weights: a name in :data:`WEIGHTS`, or one of the run's ``average_probes``; a run
            trained with ``TrainConfig.ema_decay`` is evaluated with its moving average
            unless "raw" is asked for.

    Returns:
        ``(model, info)``: the model in eval mode on ``device``, and its configs.

    Raises:
        CheckpointError: the checkpoint is missing, corrupt or of another format, or
            "ema" is asked of a run without an average, or a probe it did not keep (one
            line).
    """
    path = Path(run_dir) / CHECKPOINT_NAME
    if weights not in WEIGHTS:
        try:
            parse_probe(weights)
        except ValueError:
            raise ValueError(
                f"load_run: weights must be one of {list(WEIGHTS)} or an average probe's "
                f"name (e.g. ema0.9995, tail0.8), got {weights!r}"
            ) from None
    ckpt = read_checkpoint(path)
    probes = ckpt.get("model_average_probes") or {}
    if weights not in WEIGHTS and weights not in probes:
        kept = ", ".join(sorted(probes)) or "none"
        raise CheckpointError(
            f"{path}: kept no average probe {weights!r} (kept: {kept}); train with "
            f"TrainConfig.average_probes=({weights!r},) to score it"
        )
    ema = probes[weights]["model"] if weights in probes else ckpt.get("model_ema")
    if weights == "ema" and ema is None:
        raise CheckpointError(
            f"{path}: holds no averaged weights (trained without ema_decay); use the raw weights"
        )
    use_ema = ema is not None and weights != "raw"
    try:
        mcfg = ModelConfig.from_dict(ckpt["model_config"])
        tcfg = TrainConfig.from_dict(ckpt["train_config"])
        model = SVORF(mcfg)
        model.load_state_dict(ema if use_ema else ckpt["model"])
    except (ValueError, RuntimeError, TypeError) as e:
        msg = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
        raise CheckpointError(f"{path}: checkpoint does not match this code ({msg[:160]})") from e
    model.to(torch.device(device) if isinstance(device, str) else device).eval()
    info = RunInfo(
        mcfg,
        tcfg,
        int(ckpt["step"]),
        dict(ckpt.get("dataset", {})),
        float(ckpt.get("wall_s", 0.0)),
        weights if weights in probes else "ema" if use_ema else "raw",
    )
    return model, info


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


def render_probe(model: SVORF, changes: dict[str, Any]) -> SVORF:
    """Render ``model`` with other values of scene-prior or sampling fields
    (:data:`RENDER_PROBE_FIELDS`).

    E.g. ``{"fg_zmin": 0.10}`` bars the object slots from the band 0.05-0.10 above the
    floor at render time: how much of the segmentation's error lives there, before a
    training run with that value is spent; ``{"n_fine": 64}`` renders with more samples
    per ray (is an error the quadrature's?); ``{"comp_temperature": 0.5}`` sharpens the
    slot-guided soft masks m (is an error the masks' softness or the fields'?);
    ``{"eval_mask_rule": "peak"}`` reads each pixel's masks from its largest-weight sample
    (is the rim a half-transparent rind in front of the floor?), ``"peak_background"``
    lets that sample decide only background against object. The model
    is changed in place and returned.

    Raises:
        ValueError: a field that is not a render-time prior, or a value the config refuses
            (one line).
    """
    bad = sorted(set(changes) - set(RENDER_PROBE_FIELDS))
    if bad:
        raise ValueError(
            f"render probe: {', '.join(bad)} cannot change at render time (the weights depend "
            f"on it); fields that can: {', '.join(RENDER_PROBE_FIELDS)}"
        )
    model.cfg = model.cfg.replace(**changes)
    if "comp_temperature" in changes and hasattr(model.composer, "temperature"):
        model.composer.temperature = float(model.cfg.comp_temperature)
    return model
