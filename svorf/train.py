"""Training loop of sVORF: :func:`train`, its steps, and the run folder's logs.

Where this sits: ``svorf.data`` (dataset + ray sampler) -> **here** (Adam with linear
warm-up, paper appendix A; the optimizer in ``svorf.optim``) -> checkpoints in a run folder
(``svorf.checkpoint``) -> ``load_run`` / ``predict_scene`` (``svorf.checkpoint``,
``svorf.predict``) for ``svorf render`` and the benchmark adapter. The configs
(``TrainConfig``, ``run_configs``, ``config_key``) are in ``svorf.train_config``, what the
scales, presets and the cpu recipe set in ``svorf.registry``. This module re-exports the
public names of ``train_config``, ``checkpoint`` and ``predict`` (their old home): callers
keep importing them from ``svorf.train``; ``TrainSummary``, ``TrainingDiverged`` and the
wall-time ``Budget`` live in ``svorf.run_records``.

A run folder holds::

    checkpoint.pt   latest good state (atomic temp + os.replace): model, optimizer, step,
                    RNG states, configs as JSON dicts, dataset fingerprint, budget
    config.json     the same configs, for people
    log.jsonl       one line per logged step: step, wall_s, lr, loss, parts, steps_per_s
    eval.jsonl      one line per held-out evaluation: step, wall_s, metrics
    summary.json    what :func:`train` returns (``TrainSummary.to_dict()``)

:func:`train` runs these steps: :func:`_setup` (device, data, ray samplers, model,
optimizer), :func:`_start` (:func:`_resume` from the checkpoint or start afresh,
``--init-from``, ``config.json``), then per optimizer step :func:`_train_step` (learning
rate, batch, forward, backward, with the NaN guards :func:`_guard_loss` and
:func:`_guard_grad`), the log line, the held-out evaluation (:func:`_run_eval`) and the
checkpoint (:func:`_save`), all timed by the wall-time budget (:class:`Budget`); finally
:func:`_finish` writes the summary.

Determinism: parameters are initialised after ``torch.manual_seed(seed)``; scenes,
input views and rays come from a ``torch.Generator`` seeded with ``seed``; the model's
own randomness (stratified sampling jitter, the packed-11 slot mask) uses the global
torch RNG. All of these states are checkpointed, so ``resume=True`` (same budget) goes on
as the uninterrupted run step for step (bit-identical on the same machine and device).

Data parallel: under ``torchrun`` (a process group initialised by ``svorf.cli`` through
``svorf.distributed.init_from_env``) :func:`train` splits every step's global batch of
``batch_scenes`` scenes over the ranks and averages the gradients; rank 0 writes the run
folder. The result matches a single-process run with the same configs up to float
summation order (see ``svorf.distributed`` for how the random draws are kept identical).

Nothing here imports ``benchmark`` or ``generators`` (svorf stands alone): held-out
metrics such as ARI are plugged in by the caller through ``eval_fn``.
"""

from __future__ import annotations

import contextlib
import math
import os
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

from scenefmt import atomic_write_json
from scenefmt.cli_util import progress_kwargs
from svorf import distributed
from svorf.checkpoint import (
    CHECKPOINT_FORMAT,
    CHECKPOINT_NAME,
    CheckpointError,
    RunInfo,
    atomic_torch_save,
    check_resumable,
    init_weights_from,
    load_run,
    read_checkpoint,
    restore_checkpoint,
    write_checkpoint,
)
from svorf.config import ModelConfig, bf16_autocast_on
from svorf.data import (
    MultiViewDataset,
    RayBatch,
    RaySampler,
    dataset_fingerprint,
    gray_some_scenes,
)
from svorf.model import SVORF
from svorf.optim import ProbeAverages, WeightAverage, grad_norm, make_optimizer, param_groups
from svorf.predict import ScenePrediction, default_eval, predict_scene
from svorf.ray_sampling import ErrorMap
from svorf.refine import refine_batch
from svorf.run_records import (
    Budget,
    TrainingDiverged,
    TrainSummary,
    append_jsonl,
    log_step,
    peak_rss_mb,
    recipe_rate_check,
    truncate_jsonl,
)
from svorf.train_config import (
    BOOKKEEPING_FIELDS,
    CPU_RECIPE,
    CPU_RECIPE_MODEL_FIELDS,
    CPU_RECIPE_PRESETS,
    LR_DECAYS,
    PRESETS,
    SCALES,
    PresetSpec,
    TrainConfig,
    apply_recipe,
    config_key,
    learning_fields,
    lr_at,
    recipe_applies,
    resolve_device,
    run_configs,
    train_config,
)

# With the names re-exported from svorf.train_config, svorf.checkpoint and svorf.predict.
__all__ = [
    "BOOKKEEPING_FIELDS",
    "CHECKPOINT_FORMAT",
    "CHECKPOINT_NAME",
    "CPU_RECIPE",
    "CPU_RECIPE_MODEL_FIELDS",
    "CPU_RECIPE_PRESETS",
    "LR_DECAYS",
    "PRESETS",
    "SCALES",
    "CheckpointError",
    "EvalFn",
    "PresetSpec",
    "RunInfo",
    "ScenePrediction",
    "TrainConfig",
    "TrainSummary",
    "TrainingDiverged",
    "apply_recipe",
    "atomic_torch_save",
    "config_key",
    "dataset_fingerprint",
    "default_eval",
    "init_weights_from",
    "learning_fields",
    "load_run",
    "lr_at",
    "predict_scene",
    "read_checkpoint",
    "recipe_applies",
    "resolve_device",
    "run_configs",
    "train",
    "train_config",
]

#: Signature of a held-out evaluation hook: ``eval_fn(model, dataset) -> {name: float}``.
#: The model is in eval mode and the global RNG is forked around the call.
EvalFn = Callable[[SVORF, MultiViewDataset], dict[str, float]]


# --------------------------------------------------------------------------- training


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
) -> TrainSummary:
    """Train sVORF on a split folder and write a run folder.

    Args:
        data_dir: training split (``svorf.data.MultiViewDataset`` reads it at
            ``model_cfg.image_size``, or at ``train_cfg.target_size`` when that is set).
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
        The run's :class:`TrainSummary` (``steps``, ``start_step``, ``final_loss``,
        ``wall_s`` of this call, ``train_wall_s`` of all calls, ``s_per_step``, ...), also
        written to ``summary.json``.

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
    run = _setup(data_dir, out_dir, model_cfg, train_cfg, eval_data, max_scenes, resume)
    run.max_wall_s = max_wall_s
    _start(run, resume, data_dir, init_from)
    cfg = run.train_cfg
    bar = _progress_bar(run) if progress and run.main else None
    run.model.train()
    budget = Budget(run.wall_offset, max_wall_s)
    last_log_t, last_log_step = budget.t0, run.start
    params = [p for p in run.model.parameters() if p.requires_grad]
    rate_check = recipe_rate_check(run.model_cfg, cfg, run.device, max_wall_s, run.main)
    try:
        for step in range(run.start, cfg.steps):
            lr, parts, gnorm = _train_step(run, step, budget.progress(step, cfg.steps), params)
            done = step + 1
            if bar is not None:
                bar.update(1)
                bar.set_postfix(loss=f"{run.last_loss:.5f}")
            now = time.perf_counter()
            wall = budget.wall(now)
            if run.dctx is not None and max_wall_s is not None:  # all ranks stop at one step
                wall = distributed.all_reduce_max(wall, run.device)
            out_of_time = budget.spent(wall)
            if rate_check is not None and rate_check.speak(
                done, wall, run.wall_offset, cfg.steps, bar
            ):
                rate_check = None  # once
            if run.main and (done % cfg.log_every == 0 or done == cfg.steps or out_of_time):
                sps = (done - last_log_step) / max(now - last_log_t, 1e-9)
                log_step(run.log_path, done, wall, lr, run.last_loss, parts, gnorm, sps)
                last_log_t, last_log_step = now, done
            with budget.paused_while():  # eval and checkpoint time is not training time
                if run.eval_ds is not None and done % cfg.eval_every == 0:
                    _run_eval(run, eval_fn, done, wall)
                if done % cfg.ckpt_every == 0 or done == cfg.steps or out_of_time:
                    if run.main:
                        _save(run, done, wall)
                    run.saved = done
            if out_of_time:
                break
    finally:
        if bar is not None:
            bar.close()
    return _finish(run, budget)


@dataclass
class _Run:
    """The state of one :func:`train` call that its steps share."""

    out: Path
    ckpt_path: Path
    log_path: Path
    eval_path: Path
    model_cfg: ModelConfig
    train_cfg: TrainConfig
    device: torch.device
    dctx: distributed.DistContext | None
    """The process group under torchrun, else None."""
    main: bool
    """Whether this process writes files and logs (rank 0, or the only process)."""
    lo: int
    hi: int
    """This process's rows ``[lo, hi)`` of every global batch."""
    dataset: MultiViewDataset
    eval_ds: MultiViewDataset | None
    sampler: RaySampler
    sampler_warm: RaySampler
    """The sampler of the ``nvs_warmup`` steps (``sampler`` itself without warm-up)."""
    error_map: ErrorMap | None
    """``"error_driven"`` ray sampling's map, fed with every step's per-ray errors."""
    data_info: dict[str, Any]
    gen: torch.Generator
    model: torch.nn.Module
    """The SVORF (wrapped for data parallelism under torchrun)."""
    opt: torch.optim.Optimizer
    start: int = 0
    wall_offset: float = 0.0
    """Training wall time of the earlier calls of a resumed run."""
    max_wall_s: float | None = None  # train(max_wall_s=...): the budget, kept in checkpoints
    last_loss: float = math.nan
    init_info: dict[str, Any] | None = None
    saved: int | None = None
    """The step of the checkpoint on disk, None before the first one."""
    average: WeightAverage | None = None
    probes: ProbeAverages | None = None
    """``TrainConfig.average_probes``: extra averages for comparison, never used."""


def _setup(
    data_dir: str | os.PathLike,
    out_dir: str | os.PathLike,
    model_cfg: ModelConfig,
    train_cfg: TrainConfig,
    eval_data: str | os.PathLike | None,
    max_scenes: int | None,
    resume: bool,
) -> _Run:
    """Step 1: device and process group, data, ray samplers, seeded model and optimizer."""
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
    target = train_cfg.target_size or model_cfg.image_size
    if target < model_cfg.image_size:
        raise ValueError(
            f"TrainConfig.target_size {target} is below the encoder's image_size "
            f"{model_cfg.image_size}; pass a target_size >= {model_cfg.image_size} or None"
        )
    dataset = MultiViewDataset(data_dir, image_size=target, max_scenes=max_scenes, truth=False)
    eval_ds = None
    if main and eval_data is not None and train_cfg.eval_every:
        eval_ds = MultiViewDataset(
            eval_data, image_size=model_cfg.image_size, max_scenes=train_cfg.eval_scenes
        )
    sampler, sampler_warm = _samplers(dataset, model_cfg, train_cfg)
    error_map = sampler.error_map  # "error_driven": fed with every step's per-ray errors
    if error_map is not None and dctx is not None:
        raise ValueError(
            f"ray_sampling={train_cfg.ray_sampling!r} keeps per-process error maps and is not "
            f"supported under torchrun; use 'object_heavy' or 'uniform' there"
        )
    # image_hw: the resolution the model renders and is evaluated at (svorf render, edit)
    hw = [model_cfg.image_size] * 2 if train_cfg.target_size else list(dataset.image_hw)
    data_info = {
        "fingerprint": dataset.fingerprint,
        "root": str(Path(data_dir).resolve()),
        "n_scenes": len(dataset),
        "image_hw": hw,
        "preset": dataset.preset,
    }
    if train_cfg.target_size:
        data_info["target_hw"] = list(dataset.image_hw)

    torch.manual_seed(train_cfg.seed)
    gen = torch.Generator().manual_seed(train_cfg.seed)
    model: torch.nn.Module = SVORF(model_cfg).to(device)
    if dctx is not None:
        model = distributed.prepare_model(model, device, dctx)
    groups = param_groups(getattr(model, "module", model), train_cfg.enc_lr_scale)
    opt = make_optimizer(groups, lr_at(train_cfg, 0), train_cfg.betas, device)
    out.mkdir(parents=True, exist_ok=True)
    ema = train_cfg.ema_decay
    average = WeightAverage(model.named_parameters(), ema) if ema else None
    probes = None
    if train_cfg.average_probes:
        probes = ProbeAverages(train_cfg.average_probes, model.named_parameters())
    return _Run(
        out=out,
        ckpt_path=ckpt_path,
        log_path=out / "log.jsonl",
        eval_path=out / "eval.jsonl",
        model_cfg=model_cfg,
        train_cfg=train_cfg,
        device=device,
        dctx=dctx,
        main=main,
        lo=lo,
        hi=hi,
        dataset=dataset,
        eval_ds=eval_ds,
        sampler=sampler,
        sampler_warm=sampler_warm,
        error_map=error_map,
        data_info=data_info,
        gen=gen,
        model=model,
        opt=opt,
        average=average,
        probes=probes,
    )


def _samplers(
    dataset: MultiViewDataset, model_cfg: ModelConfig, train_cfg: TrainConfig
) -> tuple[RaySampler, RaySampler]:
    """The run's ray sampler, and the one of the ``nvs_warmup`` steps (rays from the
    input view; the same sampler when there is no warm-up). They share one ErrorMap."""
    size = model_cfg.image_size if train_cfg.target_size else None  # the encoder's input
    sampler = RaySampler(
        dataset,
        train_cfg.rays_per_scene,
        nvs=model_cfg.nvs,
        ray_sampling=train_cfg.ray_sampling,
        input_size=size,
    )
    if not (train_cfg.nvs_warmup and model_cfg.nvs):
        return sampler, sampler
    warm = RaySampler(
        dataset,
        train_cfg.rays_per_scene,
        nvs=False,
        ray_sampling=train_cfg.ray_sampling,
        error_map=sampler.error_map,
        input_size=size,
    )
    return sampler, warm


def _start(
    run: _Run, resume: bool, data_dir: str | os.PathLike, init_from: str | os.PathLike | None
) -> None:
    """Step 2: resume from the run folder's checkpoint (:func:`_resume`) or start afresh
    (old logs removed), load ``init_from`` weights at step 0, write ``config.json``."""
    if resume and run.ckpt_path.exists():
        _resume(run, data_dir)
    elif run.main:
        for p in (run.log_path, run.eval_path):
            p.unlink(missing_ok=True)
    if init_from is not None and run.start == 0:
        run.init_info = init_weights_from(getattr(run.model, "module", run.model), init_from)
        if run.average is not None:
            run.average.load(run.model.state_dict())
        if run.probes is not None:
            run.probes.load(None, run.model.state_dict())
    if run.dctx is not None:  # identical already (same seed / checkpoint); made certain here
        distributed.broadcast_module(run.model)
    if run.main:
        atomic_write_json(
            run.out / "config.json",
            {
                "model": run.model_cfg.to_dict(),
                "train": run.train_cfg.to_dict(),
                "dataset": run.data_info,
                **({"init_from": run.init_info} if run.init_info else {}),
            },
        )
    run.saved = run.start if run.ckpt_path.exists() else None


def _resume(run: _Run, data_dir: str | os.PathLike) -> None:
    """Restore the checkpoint of the run folder after checking that it is this run's
    (configs, data); drop log lines written after it."""
    ckpt = read_checkpoint(run.ckpt_path)
    check_resumable(ckpt, run.ckpt_path, run.model_cfg, run.train_cfg, run.dataset.fingerprint,
                    data_dir, max_wall_s=run.max_wall_s)  # fmt: skip
    restore_checkpoint(ckpt, run.ckpt_path, run.model, run.opt, run.gen, run.device, run.error_map)
    run.start, run.wall_offset = int(ckpt["step"]), float(ckpt.get("wall_s", 0.0))
    run.last_loss = float(ckpt.get("loss", math.nan))
    run.init_info = ckpt.get("init_from")
    if run.average is not None:  # the checkpoint's average (none before ema_decay: the weights)
        run.average.load(ckpt.get("model_ema") or run.model.state_dict())
    if run.probes is not None:
        run.probes.load(ckpt.get("model_average_probes"), run.model.state_dict())
    # The state now lives in model/optimizer; the checkpoint's own copy of the weights
    # would otherwise stay alive (a second copy of the model) for the whole run.
    del ckpt
    if run.main:
        truncate_jsonl(run.log_path, run.start)
        truncate_jsonl(run.eval_path, run.start)


def _progress_bar(run: _Run) -> Any:
    """A tqdm bar over the run's steps (stderr)."""
    from tqdm import tqdm

    return tqdm(
        total=run.train_cfg.steps,
        initial=run.start,
        desc="svorf train",
        unit="step",
        dynamic_ncols=True,
        **progress_kwargs(),
    )


def _train_step(
    run: _Run, step: int, progress: float, params: list[torch.nn.Parameter]
) -> tuple[float, dict[str, Tensor], Tensor]:
    """One optimizer step (0-based ``step``): learning rate, batch, forward, backward, the
    NaN guard, Adam. Returns ``(lr, loss parts, gradient norm)``; ``run.last_loss`` too.

    Under torchrun every rank draws the whole global batch (the same draws as one
    process), keeps its rows, and the gradients and loss are averaged over the ranks
    before the guard, so all ranks stop at the same step.
    """
    cfg, model, opt = run.train_cfg, run.model, run.opt
    lr = lr_at(cfg, step, progress)
    for group in opt.param_groups:
        group["lr"] = lr * group.get("lr_scale", 1.0)
    getattr(model, "module", model).set_progress(progress)
    smp = run.sampler_warm if step < cfg.nvs_warmup else run.sampler
    share, with_input = cfg.salient_share(progress), cfg.input_view_targeted(progress)
    scenes = smp.sample_scenes(cfg.batch_scenes, run.gen)
    stride = cfg.ray_stride(progress)
    batch = smp.sample(scenes, run.gen, share, with_input, cfg.pixel_jitter, stride)
    if cfg.gray_scenes > 0:
        batch = gray_some_scenes(batch, cfg.gray_scenes, run.gen)
    iterative = cfg.refine_train is not None and step >= cfg.nvs_warmup
    # The input views' pixels of the refinement, drawn for the whole global batch.
    inp = _input_pixels(smp.dataset, batch, cfg.refine_train[2], run.gen) if iterative else ()
    if run.dctx is not None:
        batch = _batch_rows(batch, run.lo, run.hi)
        inp = tuple(x[run.lo : run.hi] for x in inp)
    batch = batch.to(run.device)
    with _batch_random(run):
        if cfg.slot_distill is not None and step >= cfg.nvs_warmup:
            out_r, loss, parts = _distill_forward(run, batch)
        elif iterative:
            out_r, loss, parts = _iterative_forward(run, batch, inp)
        else:
            # In train mode the model draws the packed-11 slot mask itself (global RNG).
            out_r = model(
                batch.images, batch.rays_o, batch.rays_d, perturb=True, input_c2w=batch.input_c2w
            )
            loss, parts = model.loss(out_r, batch.target_rgb)
    if run.error_map is not None:
        run.error_map.update(
            batch.scenes,
            batch.target_view,
            batch.target_pixel,
            (out_r.rgb.detach() - batch.target_rgb).pow(2).mean(-1),
        )
    done = step + 1
    if run.dctx is not None:
        loss.backward()
        loss, parts = _average_step(params, loss, parts, run.dctx.world_size)
    _guard_loss(run, done, loss, parts)
    if run.dctx is None:
        loss.backward()
    gnorm = grad_norm(model.parameters())
    _guard_grad(run, done, loss, gnorm)
    opt.step()
    # Gradients never outlive their step: the next forward, where activations peak, and
    # the logging, checkpoint and evaluation in between run without them (one copy of
    # the parameters less in memory; the same numbers, as backward starts from None).
    opt.zero_grad(set_to_none=True)
    if run.average is not None:
        run.average.update(done)
    if run.probes is not None:
        run.probes.update(done, progress)
    run.last_loss = float(loss.detach())
    return lr, parts, gnorm


def _distill_forward(run: _Run, batch: RayBatch) -> tuple[Any, Tensor, dict[str, Tensor]]:
    """The step's forward under ``TrainConfig.slot_distill``: the model's forward and loss,
    plus ``weight`` times the mean squared distance of the encoder's slots to the same slots
    refined on the step's own target rays (a fixed target). Adds the loss parts
    "slot_distill" (the distance) and "refine_gain" (the refinement's MSE, first over last
    step)."""
    model = run.model
    weight, steps, lr = run.train_cfg.slot_distill
    slots, extra = model.encode_for_render(batch.images)
    kw: dict[str, Any] = {"perturb": True, "input_c2w": batch.input_c2w, **extra}
    if model.training and model.cfg.slot_mask_train > 0:
        kw["slot_mask"] = model.sample_slot_mask(slots.shape[0], device=slots.device)
    out_r = model.render_rays(slots, batch.rays_o, batch.rays_d, **kw)
    loss, parts = model.loss(out_r, batch.target_rgb)
    target, mse = refine_batch(
        model,
        slots,
        batch.rays_o,
        batch.rays_d,
        batch.target_rgb,
        steps=steps,
        lr=lr,
        input_c2w=batch.input_c2w,
        slot_mask=kw.get("slot_mask"),
    )
    dist = torch.nn.functional.mse_loss(slots.float(), target)
    loss = loss + weight * dist
    parts = {
        **parts,
        "total": loss.detach(),
        "slot_distill": dist.detach(),
        "refine_gain": mse[0] / mse[1].clamp_min(1e-12),
    }
    return out_r, loss, parts


def _input_pixels(
    dataset: MultiViewDataset, batch: RayBatch, rays: int, generator: torch.Generator
) -> tuple[Tensor, Tensor, Tensor]:
    """``(rays_o, rays_d, rgb)`` [B, rays, 3] through uniformly drawn pixels of each batch
    scene's input view, at the dataset's resolution (``TrainConfig.refine_train``)."""
    (h, w), v_all = dataset.image_hw, dataset.n_views
    pix = torch.randint(0, h * w, (len(batch.scenes), rays), generator=generator)
    out: tuple[list[Tensor], list[Tensor], list[Tensor]] = ([], [], [])
    for i, (s, iv) in enumerate(zip(batch.scenes.tolist(), batch.input_view.tolist())):
        o, d = dataset.rays(s, torch.full((rays,), iv, dtype=torch.long), pix[i])
        out[0].append(o)
        out[1].append(d)
        out[2].append(dataset._rgb[s].reshape(v_all, h * w, 3)[iv, pix[i]].float() / 255.0)
    return tuple(torch.stack(x) for x in out)  # type: ignore[return-value]


def _iterative_forward(
    run: _Run, batch: RayBatch, inp: tuple[Tensor, ...]
) -> tuple[Any, Tensor, dict[str, Tensor]]:
    """The step's forward under ``TrainConfig.refine_train``: the encoder's slots refined on
    the input views' pixels ``inp`` (networks frozen), the target rays rendered from the
    refined slots, the encoder's gradient through the refinement as the identity. Adds the
    loss part "refine_gain" (the refinement's MSE on those pixels, first over last step)."""
    model = run.model
    steps, lr, _ = run.train_cfg.refine_train
    slots, extra = model.encode_for_render(batch.images)
    slot_mask = None
    if model.training and model.cfg.slot_mask_train > 0:
        slot_mask = model.sample_slot_mask(slots.shape[0], device=slots.device)
    o, d, rgb = (x.to(run.device) for x in inp)
    refined, mse = refine_batch(
        model, slots, o, d, rgb, steps=steps, lr=lr, input_c2w=batch.input_c2w,
        slot_mask=slot_mask,
    )  # fmt: skip
    slots = slots + (refined.to(slots.dtype) - slots.detach())
    out_r = model.render_rays(
        slots, batch.rays_o, batch.rays_d, perturb=True, input_c2w=batch.input_c2w,
        slot_mask=slot_mask, **extra,
    )  # fmt: skip
    loss, parts = model.loss(out_r, batch.target_rgb)
    return out_r, loss, {**parts, "refine_gain": mse[0] / mse[1].clamp_min(1e-12)}


def _batch_random(run: _Run) -> contextlib.AbstractContextManager:
    """Where the model draws its random numbers: as is in one process; under torchrun,
    as one process would for the whole global batch (``GlobalBatchRandom``)."""
    if run.dctx is None:
        return contextlib.nullcontext()
    return distributed.GlobalBatchRandom(run.dctx.rank, run.dctx.world_size, run.hi - run.lo)


def _guard_loss(run: _Run, done: int, loss: Tensor, parts: dict[str, Tensor]) -> None:
    """NaN guard of step ``done``, before backward: the loss must be finite.

    Raises:
        TrainingDiverged: naming the step, the loss parts and the checkpoint that keeps
            the last good state (it is not overwritten).
    """
    if not torch.isfinite(loss):
        shown = ", ".join(f"{k}={float(v):.4g}" for k, v in parts.items())
        raise TrainingDiverged(
            f"non-finite loss {float(loss.detach())} at step {done} ({shown}); {_kept(run)}",
            step=done,
        )


def _guard_grad(run: _Run, done: int, loss: Tensor, gnorm: Tensor) -> None:
    """NaN guard of step ``done``, before the optimizer step: the gradient norm must be
    finite.

    Raises:
        TrainingDiverged: naming the step and the checkpoint that keeps the last good state.
    """
    if not torch.isfinite(gnorm):
        raise TrainingDiverged(
            f"non-finite gradient norm at step {done} (loss {float(loss.detach()):.6g}); "
            f"{_kept(run)}",
            step=done,
        )


def _kept(run: _Run) -> str:
    """What a diverged run leaves on disk (for the TrainingDiverged message)."""
    if run.saved is None:
        return "no checkpoint was written yet"
    return f"{run.ckpt_path} keeps the last good state (step {run.saved})"


def _run_eval(run: _Run, eval_fn: EvalFn | None, step: int, wall: float) -> None:
    """The held-out evaluation after ``step`` steps (model in eval mode, RNG forked);
    appends a line to ``eval.jsonl``."""
    assert run.eval_ds is not None
    fn = eval_fn or (lambda m, d: default_eval(m, d, run.train_cfg.eval_scenes))
    model = run.model
    model.eval()
    try:
        forked = [run.device] if run.device.type == "cuda" else []
        with torch.random.fork_rng(devices=forked), torch.no_grad():
            metrics = fn(model, run.eval_ds)
    finally:
        model.train()
    append_jsonl(
        run.eval_path,
        {"step": step, "wall_s": round(wall, 3), **{k: float(v) for k, v in metrics.items()}},
    )


def _save(run: _Run, step: int, wall: float) -> None:
    """Write the checkpoint after ``step`` steps (training wall time ``wall``)."""
    write_checkpoint(
        run.ckpt_path,
        step=step,
        model=run.model,
        optimizer=run.opt,
        gen=run.gen,
        device=run.device,
        model_cfg=run.model_cfg,
        train_cfg=run.train_cfg,
        dataset=run.data_info,
        wall_s=wall,
        loss=run.last_loss,
        max_wall_s=run.max_wall_s,
        error_map=run.error_map,
        init_from=run.init_info,
        model_ema=run.average.state_dict(run.model.state_dict()) if run.average else None,
        average_probes=run.probes.state_dict(run.model.state_dict()) if run.probes else None,
    )


def _finish(run: _Run, budget: Budget) -> TrainSummary:
    """The run summary (written to ``summary.json`` by the main process)."""
    elapsed = time.perf_counter() - budget.t0
    end = run.saved if run.saved is not None else run.start
    steps_run = max(end - run.start, 0)
    paused = budget.paused
    summary = TrainSummary(
        steps=end,
        start_step=run.start,
        final_loss=run.last_loss,
        wall_s=round(elapsed, 3),
        train_wall_s=round(run.wall_offset + elapsed - paused, 3),
        s_per_step=round((elapsed - paused) / steps_run, 5) if steps_run else math.nan,
        peak_rss_mb=round(peak_rss_mb(), 1),
        params=run.model.count_parameters(),
        device=str(run.device),
        # What bf16_autocast resolved to on this device ("auto": native bf16 only).
        bf16_autocast_active=bf16_autocast_on(run.model_cfg.bf16_autocast, run.device),
        checkpoint=str(run.ckpt_path),
        log=str(run.log_path),
        dataset_fingerprint=run.dataset.fingerprint,
        init_from=run.init_info,
        world_size=run.dctx.world_size if run.dctx is not None else None,
    )
    if run.main:
        atomic_write_json(run.out / "summary.json", summary.to_dict())
    return summary


# --------------------------------------------------------------------------- data parallel


def _batch_rows(batch: RayBatch, lo: int, hi: int) -> RayBatch:
    """Scenes ``[lo, hi)`` of a batch (this rank's share of the global batch)."""
    return RayBatch(**{k: getattr(batch, k)[lo:hi] for k in batch.__dataclass_fields__})


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
