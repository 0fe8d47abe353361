"""Speed of a training step for each speed knob of ModelConfig, and each knob's error.

Where it sits: a measuring tool of the model, in the benchmark's tools package (training
does not use it; the ``tradeoff`` protocol times its curves with :func:`time_interleaved`,
the project's one interleaved timing loop). It builds one model per variant (same weights),
then times (a) forward + loss + backward of a batch like one training step (default 4 scenes
x 256 rays, the cpu scale's) and (b) the per-point evaluation alone (hypernetwork, slot
masks, object fields, composition at every sample, forward + backward), with the variants
**interleaved** (repeat r runs every variant once, in turn), so that the load of other
processes on a shared 2-core machine hits them alike; it reports medians and ratios to the
model without any speed knob (``original``). It also reports, per variant, how far its
evaluation render (no jitter, same weights, same rays) is from the knob-free model's: the
time-vs-error pair of each knob; and, in a fresh subprocess per variant, the peak resident
memory of a few training steps.

Usage::

    python -m benchmark.tools.speedbench --scale cpu [--repeats 7] [--json out.json] [--no-rss]

``--recipe`` applies the cpu recipe's model levers (``benchmark.tools.recipe.RECIPE_LEVERS``)
to every variant, so the knobs are timed on the model the recipe trains.

``--optimizer`` times, instead of the variants, a whole training step (forward, backward,
gradient norm, Adam) with the training loop's fused Adam (``svorf.optim``) against
per-tensor Adam, and how far one update of each lands apart (:func:`optimizer_run`).

Variants: ``original`` (every knob off, the composer in its paper form
``SlotGuidedComposer.logits_reference``, the decoder's cross-attention in its textbook form
``MultiHeadAttention.forward_reference`` and the encoder's convolutions in the default
layout: the model before any speed work, the reference of every ratio), ``baseline`` (every
knob off: the paper's method, with the exact folded composer, folded cross-attention and
channels-last encoder), ``baseline-unfolded-encode`` and ``default-unfolded-encode``
(baseline and default with the original's encode),
one per knob, ``all`` (every knob), ``default`` (what ``model_config(scale)`` turns on).
The ``sharp-m`` variants scale the composition logits (x ``--sharpen``) in *both* the
variant and its error reference ``sharp-m baseline``, to mimic a trained model whose slot
masks m are nearly one-hot (at initialisation m is nearly uniform over the K slots); they
show what top-k / keep-mass selection saves once slots own regions.

Output JSON (``--json``): ``{"scale", "batch": {"scenes", "rays"}, "threads", "repeats",
"block", "torch", "time_reference", "config", "variants": [{"name", "overrides", "sharpen",
"median_s", "steps_per_s", "ratio" (original median / this median), "ratio_vs_baseline",
"query_s", "query_ratio" (per-point evaluation alone),
"kept_pairs", "rgb_max_err", "rgb_mean_err", "depth_mean_err", "slot_probs_max_err",
"peak_rss_mb"}]}``; times in seconds, errors in colour units [0, 1] / world units.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import resource
import statistics
import subprocess
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path
from typing import Any

import torch
import torch.nn.functional as F
from torch import Tensor

from scenefmt import mkstemp_beside
from scenefmt.cli_util import DefaultsFormatter, doc_summary
from svorf.compose import masked_softmax
from svorf.config import ModelConfig, bf16_native, model_config
from svorf.model import SVORF
from svorf.optim import grad_norm, make_optimizer
from svorf.render import clip_rays_to_box, sample_stratified

# Every knob off: the paper's method at the scale's sizes.
KNOBS_OFF: dict[str, Any] = {
    "bf16_autocast": False,
    "enc_bf16": False,
    "fg_box": None,
    "slot_topk": 0,
    "slot_keep_mass": 1.0,
}


@dataclass
class Variant:
    """One configuration to time: ``overrides`` on top of the scale's config with every knob
    off; ``sharpen`` multiplies the composition logits (also in its reference baseline)."""

    name: str
    overrides: dict[str, Any]
    sharpen: float = 1.0
    reference: bool = False
    """The knob-free model that errors of variants with the same ``sharpen`` are taken
    against (the first reference of the list is also the time reference of every ratio)."""
    paper_form_composer: bool = False
    """Run the composer as written in the paper (``logits_reference``, softmax over the last
    axis): the code path before the folded composer."""
    reference_encode: bool = False
    """Encode as before the encode-side speed work: the encoder's convolutions in PyTorch's
    default layout (``ImageEncoder.channels_last_on_cpu`` off) and the decoder's
    cross-attention in its textbook form (``MultiHeadAttention.forward_reference``)."""
    times: list[float] = field(default_factory=list)
    query_times: list[float] = field(default_factory=list)


def default_variants(scale: str, sharpen: float = 8.0) -> list[Variant]:
    """original, baseline, one variant per knob, all knobs, the scale's defaults, and the
    sharp-m variants (left out when ``sharpen`` is 1).

    ``fg_box`` 3.75 is a foreground cube for the CLEVR-like presets (object centres within
    |x|, |y| <= 3 = ``generators`` xy_range, plus the object's size) inside the +-4.5 box.
    """
    cfg = model_config(scale)  # type: ignore[arg-type]
    defaults = {k: getattr(cfg, k) for k in KNOBS_OFF}
    every = {"bf16_autocast": True, "fg_box": 3.75, "slot_topk": 2, "slot_keep_mass": 0.99}
    dflt = {k: v for k, v in defaults.items() if KNOBS_OFF[k] != v}
    out = [
        Variant("original", {}, reference=True, paper_form_composer=True, reference_encode=True),
        Variant("baseline", {}),
        # baseline with the encode of the original: what the encode-side speed work buys
        Variant("baseline-unfolded-encode", {}, reference_encode=True),
        Variant("bf16", {"bf16_autocast": True}),
        Variant("fg_box=3.75", {"fg_box": 3.75}),
        Variant("topk=3", {"slot_topk": 3}),
        Variant("topk=2", {"slot_topk": 2}),
        Variant("keep_mass=0.99", {"slot_keep_mass": 0.99}),
        Variant("all", every),
        Variant("default", dflt),
        Variant("default-unfolded-encode", dflt, reference_encode=True),
        # the scale's defaults with the encoder's CNN in bf16 as well (a recipe lever)
        Variant("default+enc_bf16", {**dflt, "bf16_autocast": True, "enc_bf16": True}),
    ]
    if sharpen != 1.0:
        out += [
            Variant("sharp-m baseline", {}, sharpen, reference=True),
            Variant("sharp-m topk=2", {"slot_topk": 2}, sharpen),
            Variant("sharp-m keep_mass=0.99", {"slot_keep_mass": 0.99}, sharpen),
            Variant("sharp-m default", dflt, sharpen),
            Variant("sharp-m all", every, sharpen),
        ]
    return out


def make_batch(cfg: ModelConfig, scenes: int, rays: int, seed: int = 0):
    """Images [B, 3, S, S] in [0, 1], rays from ~11.7 units away into the scene box, targets."""
    g = torch.Generator().manual_seed(seed)
    s = cfg.image_size
    images = torch.rand(scenes, 3, s, s, generator=g)
    o = torch.tensor([0.0, -10.0, 6.0]).expand(scenes, rays, 3).clone()
    o = o + 0.5 * torch.randn(scenes, 1, 3, generator=g)
    target = (torch.rand(scenes, rays, 3, generator=g) - 0.5) * 2 * (cfg.box_half * 0.7)
    d = F.normalize(target - o, dim=-1)
    rgb = torch.rand(scenes, rays, 3, generator=g)
    return images, o, d, rgb


def build_model(scale: str, v: Variant, state: dict | None, seed: int = 0) -> SVORF:
    """The variant's model with the shared weights ``state`` (or seed-initialised)."""
    cfg = model_config(scale, **{**KNOBS_OFF, **v.overrides})  # type: ignore[arg-type]
    torch.manual_seed(seed)
    model = SVORF(cfg)
    if state is not None:
        model.load_state_dict(state)
    comp = model.composer
    if v.sharpen != 1.0 and comp is not None:
        with torch.no_grad():  # logits = <a_z(z), a_s(s)>: scaling a_s scales every logit
            comp.a_s.weight.mul_(v.sharpen)
            comp.a_s.bias.mul_(v.sharpen)
    if v.paper_form_composer and comp is not None:

        def paper_form(gx, slots, valid=None, bias=None):
            logits = comp.logits_reference(gx, slots, valid)  # [B, P, K]
            if comp.temperature != 1.0:
                logits = logits / comp.temperature
            if bias is not None:  # [B, K, P] (slot locality)
                logits = logits.float() + bias.transpose(1, 2)
            return masked_softmax(logits, valid)

        comp.forward = paper_form  # type: ignore[method-assign]
    if v.reference_encode:
        model.encoder.channels_last_on_cpu = False
        for mod in model.slot_module.modules():
            if hasattr(mod, "fold_keys"):
                mod.fold_keys = False
    return model.train()


def make_query_step(model: SVORF, batch):
    """A callable timing the per-point evaluation alone: hypernetwork, composition masks,
    object fields and composition (``SVORF._query``) at every sample of the batch's rays,
    forward + backward, with fixed slots; two queries (n_coarse then n_fine samples per ray)
    as in a training step."""
    images, o, d, _ = batch
    cfg = model.cfg
    with torch.no_grad():
        slots = model.encode(images)
    B, R = o.shape[:2]
    near_r, far_r = clip_rays_to_box(o, d, cfg.near, cfg.far, cfg.box_half)
    if not cfg.clip_to_box:
        near_r, far_r = torch.full_like(near_r, cfg.near), torch.full_like(far_r, cfg.far)
    g = torch.Generator().manual_seed(1)
    ts = [
        sample_stratified(near_r, far_r, R, n, True, generator=g)
        for n in (cfg.n_coarse, cfg.n_fine)
        if n
    ]
    is_bg = torch.zeros(B, slots.shape[1], dtype=torch.bool)
    is_bg[:, -1] = True

    def step() -> None:
        params = model.slot_params(slots)
        total = 0.0
        for t in ts:
            q = model._query(model.query_context(slots, params, o, d, None, is_bg), t)
            total = total + q.rgb.square().mean() + q.sigma.mean() + q.sigma_k.mean()
        total.backward()
        model.zero_grad(set_to_none=True)

    return step


def time_interleaved(
    steps: Sequence[Callable[[], object]],
    *,
    repeats: int,
    warmup: int = 0,
    sync: Callable[[], None] | None = None,
    after_step: Callable[[int], None] | None = None,
    after_warmup: Callable[[], None] | None = None,
    on_repeat: Callable[[int, list[float]], None] | None = None,
) -> list[list[float]]:
    """Wall times of every step, **interleaved**: round r runs every step once, in turn, so
    that the load of other processes hits all steps alike (this module's method; the
    benchmark's ``tradeoff`` protocol times its points with it too).

    Args:
        steps: the callables to time.
        repeats: timed rounds.
        warmup: untimed rounds first (allocator, caches).
        sync: called right before and right after each call, inside the timing (e.g.
            ``torch.cuda.synchronize``), None = nothing.
        after_step: called with the step's index after each call, outside the timing.
        after_warmup: called once between the warm-up and the timed rounds.
        on_repeat: called after each timed round with its index and that round's times.

    Returns:
        Per step, its ``repeats`` times in seconds.
    """

    def timed(i: int) -> float:
        if sync is not None:
            sync()
        t0 = time.perf_counter()
        steps[i]()
        if sync is not None:
            sync()
        dt = time.perf_counter() - t0
        if after_step is not None:
            after_step(i)
        return dt

    for _ in range(warmup):
        for i in range(len(steps)):
            timed(i)
    if after_warmup is not None:
        after_warmup()
    times: list[list[float]] = [[] for _ in steps]
    for r in range(repeats):
        for i in range(len(steps)):
            times[i].append(timed(i))
        if on_repeat is not None:
            on_repeat(r, [t[-1] for t in times])
    return times


def train_step(model: SVORF, batch, block: int = 1) -> None:
    """Forward, loss and backward of one batch (perturbed samples, as in training),
    ``block`` times in a row."""
    images, o, d, rgb = batch
    for _ in range(block):
        out = model(images, o, d, perturb=True)
        loss, _ = model.loss(out, rgb)
        model.zero_grad(set_to_none=True)
        loss.backward()


def compare_train_steps(
    models: dict[str, SVORF], batch, *, repeats: int, warmup: int = 3
) -> dict[str, Any]:
    """Median training-step time of each model on one batch, timed interleaved
    (:func:`time_interleaved`), and each median's ratio to the first model's.

    The side-by-side step price of a config change (the recipe's notes price a lever before
    training it): ``{"batch_scenes", "rays_per_scene", "threads", "repeats", "warmup",
    "median_s": {name: s}, "ratio": {name: x}}``.
    """
    names = list(models)
    steps = [lambda m=models[n]: train_step(m, batch) for n in names]
    times = time_interleaved(steps, repeats=repeats, warmup=warmup)
    med = {n: statistics.median(t) for n, t in zip(names, times)}
    first = med[names[0]]
    images, o = batch[0], batch[1]
    return {
        "batch_scenes": int(images.shape[0]),
        "rays_per_scene": int(o.shape[1]),
        "threads": torch.get_num_threads(),
        "repeats": repeats,
        "warmup": warmup,
        "median_s": med,
        "ratio": {n: t / first for n, t in med.items()},
    }


@torch.no_grad()
def render_errors(model: SVORF, ref: SVORF, batch) -> dict[str, float]:
    """Difference of ``model``'s evaluation render from ``ref``'s on the batch's rays."""
    images, o, d, _ = batch
    model.eval()
    ref.eval()
    a = model(images, o, d)
    b = ref(images, o, d)
    model.train()
    ref.train()
    return {
        "rgb_max_err": float((a.rgb - b.rgb).abs().max()),
        "rgb_mean_err": float((a.rgb - b.rgb).abs().mean()),
        "depth_mean_err": float((a.depth - b.depth).abs().mean()),
        "slot_probs_max_err": float((a.slot_probs - b.slot_probs).abs().max()),
    }


def peak_rss_subprocess(
    scale: str,
    v: Variant,
    scenes: int,
    rays: int,
    threads: int,
    weights: str | os.PathLike | None = None,
) -> float:
    """Peak RSS (MiB) of a fresh process that builds the variant (with a run's ``weights``
    where given) and runs 3 steps."""
    spec = json.dumps(
        {
            "scale": scale,
            "name": v.name,
            "overrides": v.overrides,
            "sharpen": v.sharpen,
            "paper_form_composer": v.paper_form_composer,
            "reference_encode": v.reference_encode,
            "weights": None if weights is None else str(weights),
            "scenes": scenes,
            "rays": rays,
            "threads": threads,
        }
    )
    res = subprocess.run(
        [sys.executable, "-m", "benchmark.tools.speedbench", "--_rss-worker", spec],
        capture_output=True,
        text=True,
        check=False,
    )
    if res.returncode != 0:
        raise RuntimeError(f"speedbench RSS worker for {v.name!r} failed:\n{res.stderr[-2000:]}")
    return float(res.stdout.strip().splitlines()[-1])


def _rss_worker(spec_json: str) -> None:
    spec = json.loads(spec_json)
    torch.set_num_threads(spec["threads"])
    v = Variant(
        spec["name"],
        spec["overrides"],
        spec["sharpen"],
        paper_form_composer=spec["paper_form_composer"],
        reference_encode=spec["reference_encode"],
    )
    model = build_model(spec["scale"], v, None)
    if spec.get("weights"):  # loaded before the variant's sharpening, as in run()
        model = build_model(spec["scale"], v, _run_weights(spec["weights"], model.state_dict()))
    batch = make_batch(model.cfg, spec["scenes"], spec["rays"])
    for _ in range(3):
        train_step(model, batch)
    print(_peak_rss_mb())


def _peak_rss_mb() -> float:
    """Peak resident memory of this process (MiB).

    VmHWM of /proc/self/status where there is one: it belongs to this program's own address
    space, whereas ru_maxrss also counts the parent's peak when the process was started by
    vfork + exec (as subprocess does), which made every variant report the parent's peak.
    """
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) / 1024.0  # kB
    except OSError:
        pass
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss  # KiB on Linux, bytes on macOS
    return rss / (1024.0 * 1024.0) if sys.platform == "darwin" else rss / 1024.0


def run(
    scale: str = "cpu",
    *,
    scenes: int = 4,
    rays: int = 256,
    repeats: int = 7,
    warmup: int = 2,
    threads: int = 2,
    sharpen: float = 8.0,
    rss: bool = True,
    variants: list[Variant] | None = None,
    block: int = 1,
    weights: str | os.PathLike | None = None,
    log=print,
) -> dict[str, Any]:
    """Time every variant interleaved; return the JSON-able report (see module docstring).

    ``block``: training steps a variant runs in a row per round (the times are per step).
    Training runs one model's steps back to back; with one step per round the variants'
    steps alternate, which can hide a gain that lives in warm caches (the channels-last
    encoder's: 1.10x in blocks of 5, none at 1, on the same machine and model).

    ``weights``: a training run folder whose checkpoint's weights (its moving average where
    it has one) every variant starts from, instead of a fresh initialisation: the time of a
    trained model, whose slot masks own regions (what keep-mass selection prunes depends
    on it). Its parameters must match the variants' model (same scale and recipe).
    """
    torch.set_num_threads(threads)
    variants = variants if variants is not None else default_variants(scale, sharpen)
    # Shared initial weights: from a model with the variants' non-knob overrides (e.g. the
    # recipe's slot_locality adds parameters), which every variant has in common.
    common = {k: v for k, v in variants[0].overrides.items() if k not in KNOBS_OFF}
    state = build_model(scale, Variant("init", common), None).state_dict()
    if weights is not None:
        state = _run_weights(weights, state)
    models = [build_model(scale, v, state) for v in variants]
    counters = [m.count_pairs() for m in models]
    batch = make_batch(models[0].cfg, scenes, rays)
    queries = [make_query_step(m, batch) for m in models]

    def reset_counters() -> None:
        for c in counters:
            c.reset()

    # Per variant its training step, then its per-point evaluation alone.
    steps = [s for m, q in zip(models, queries) for s in (partial(train_step, m, batch, block), q)]
    times = time_interleaved(
        steps,
        repeats=repeats,
        warmup=warmup,
        after_warmup=reset_counters,
        on_repeat=lambda r, last: log(
            f"repeat {r + 1}/{repeats}: " + " ".join(f"{t:.3f}" for t in last[0::2])
        ),
    )
    for v, step_times, query_times in zip(variants, times[0::2], times[1::2]):
        v.times.extend(t / block for t in step_times)
        v.query_times.extend(query_times)
    refs: dict[float, SVORF] = {}  # error reference of each sharpen
    for v, m in zip(variants, models):
        if v.reference:
            refs.setdefault(v.sharpen, m)
    time_ref = next((v for v in variants if v.reference), variants[0])
    ref_time = statistics.median(time_ref.times)
    ref_qtime = statistics.median(time_ref.query_times)
    base_time = next(
        (statistics.median(v.times) for v in variants if v.name == "baseline"), ref_time
    )
    rows = []
    for v, m, c in zip(variants, models, counters):
        med = statistics.median(v.times)
        ref = refs.get(v.sharpen, models[0])
        row = {
            "name": v.name,
            "overrides": v.overrides,
            "sharpen": v.sharpen,
            "median_s": med,
            "steps_per_s": 1.0 / med,
            "ratio": ref_time / med,
            "ratio_vs_baseline": base_time / med,
            "query_s": statistics.median(v.query_times),
            "query_ratio": ref_qtime / statistics.median(v.query_times),
            "kept_pairs": c.fraction,
            **render_errors(m, ref, batch),
            "peak_rss_mb": None,
        }
        if rss:
            row["peak_rss_mb"] = peak_rss_subprocess(scale, v, scenes, rays, threads, weights)
        rows.append(row)
    return {
        "scale": scale,
        "time_reference": time_ref.name,
        "batch": {"scenes": scenes, "rays": rays},
        "threads": threads,
        "repeats": repeats,
        "block": block,
        "weights": None if weights is None else str(weights),
        "torch": torch.__version__,
        "bf16_native": bf16_native("cpu"),
        "config": dataclasses.asdict(model_config(scale)),  # type: ignore[arg-type]
        "base_overrides": common,
        "variants": rows,
    }


def _run_weights(run_dir: str | os.PathLike, like: dict[str, Tensor]) -> dict[str, Tensor]:
    """The weights of a training run's checkpoint, checked against the variants' ``like``.

    Raises:
        ValueError: the run's parameters are not the variants' (one line naming the first).
    """
    from svorf.checkpoint import load_run

    model, _ = load_run(run_dir)
    state = model.state_dict()
    diff = sorted(set(state) ^ set(like)) or [
        k for k in like if tuple(state[k].shape) != tuple(like[k].shape)
    ]
    if diff:
        raise ValueError(
            f"speedbench --weights {run_dir}: its model does not match the variants' "
            f"(first difference: {diff[0]!r}); pass a run of the same scale and recipe "
            "(--recipe for a cpu-recipe run)"
        )
    return state


def optimizer_run(
    scale: str = "cpu",
    *,
    overrides: dict[str, Any] | None = None,
    scenes: int = 4,
    rays: int = 256,
    repeats: int = 7,
    warmup: int = 2,
    threads: int = 2,
    log=print,
) -> dict[str, Any]:
    """Time a whole training step (forward, loss, backward, gradient norm, Adam) with the
    training loop's optimizer (``svorf.optim``: fused Adam, :func:`svorf.optim.grad_norm`)
    against the per-tensor forms it replaced (Adam without ``fused``,
    ``clip_grad_norm_(params, inf)``), interleaved, same weights and batch; and how far one
    update of the two forms from the same gradients lands apart (largest |difference| of a
    parameter)."""
    torch.set_num_threads(threads)
    v = Variant("default", dict(overrides or {}))
    state = build_model(scale, v, None).state_dict()
    models = [build_model(scale, v, state) for _ in range(2)]
    batch = make_batch(models[0].cfg, scenes, rays)
    lr, betas = 4e-4, (0.9, 0.999)
    opts = [
        make_optimizer(m.parameters(), lr, betas, "cpu", fused=f)
        for m, f in zip(models, (False, True))
    ]

    def per_tensor() -> None:
        train_step(models[0], batch)
        torch.nn.utils.clip_grad_norm_(models[0].parameters(), float("inf"))
        opts[0].step()

    def fused() -> None:
        train_step(models[1], batch)
        grad_norm(models[1].parameters())
        opts[1].step()

    # One update of each form from the same weights and gradients.
    check = [build_model(scale, v, state) for _ in range(2)]
    train_step(check[0], batch)
    for p, q in zip(check[0].parameters(), check[1].parameters()):
        q.grad = None if p.grad is None else p.grad.clone()
    norms = [
        float(torch.nn.utils.clip_grad_norm_(check[0].parameters(), float("inf"))),
        float(grad_norm(check[1].parameters())),
    ]
    for m, f in zip(check, (False, True)):
        make_optimizer(m.parameters(), lr, betas, "cpu", fused=f).step()
    diff = max(
        float((p - q).detach().abs().max())
        for p, q in zip(check[0].parameters(), check[1].parameters())
    )
    times = time_interleaved(
        [per_tensor, fused],
        repeats=repeats,
        warmup=warmup,
        on_repeat=lambda r, last: log(
            f"repeat {r + 1}/{repeats}: " + " ".join(f"{t:.3f}" for t in last)
        ),
    )
    meds = [statistics.median(t) for t in times]
    return {
        "scale": scale,
        "batch": {"scenes": scenes, "rays": rays},
        "threads": threads,
        "repeats": repeats,
        "torch": torch.__version__,
        "overrides": v.overrides,
        "param_tensors": sum(1 for _ in models[0].parameters()),
        "forms": [
            {"name": n, "median_s": m, "steps_per_s": 1.0 / m, "times_s": t}
            for n, m, t in zip(("per-tensor", "fused"), meds, times)
        ],
        "ratio": meds[0] / meds[1],
        "grad_norms": norms,
        "update_max_abs_diff": diff,
    }


def format_table(report: dict[str, Any]) -> str:
    """Plain-text table of a :func:`run` report."""
    head = (
        f"{'variant':24s} {'steps/s':>8s} {'median s':>9s} {'ratio':>6s} {'vs base':>7s} "
        f"{'query s':>8s} {'q ratio':>7s} "
        f"{'pairs':>6s} {'rgb max':>8s} {'rgb mean':>9s} {'depth':>7s} {'m max':>7s} "
        f"{'RSS MB':>7s}"
    )
    title = (
        f"benchmark.tools.speedbench scale={report['scale']} batch={report['batch']['scenes']}x"
        f"{report['batch']['rays']} rays, threads={report['threads']}, "
        f"repeats={report['repeats']} (interleaved, medians), "
        f"block={report.get('block', 1)} steps, torch {report['torch']}"
    )
    lines = [
        title,
        head,
        "-" * len(head),
    ]
    for r in report["variants"]:
        rss = "-" if r["peak_rss_mb"] is None else f"{r['peak_rss_mb']:.0f}"
        lines.append(
            f"{r['name']:24s} {r['steps_per_s']:8.2f} {r['median_s']:9.3f} {r['ratio']:6.2f} "
            f"{r['ratio_vs_baseline']:7.2f} {r['query_s']:8.3f} {r['query_ratio']:7.2f} "
            f"{r['kept_pairs']:6.2f} {r['rgb_max_err']:8.4f} "
            f"{r['rgb_mean_err']:9.5f} {r['depth_mean_err']:7.4f} "
            f"{r['slot_probs_max_err']:7.4f} {rss:>7s}"
        )
    lines.append(
        f"ratio: {report['time_reference']} median / variant median (>1 = faster); vs base: "
        "the same against 'baseline'; query s / q ratio: the per-point evaluation alone "
        "(hypernetwork, masks, fields, composition at all n_coarse + n_fine samples, fwd+bwd); "
        "pairs: fraction of (point, slot) field evaluations kept (training steps); errors: "
        "eval render vs the knob-free model with the same weights (sharp-m rows vs "
        "'sharp-m baseline'): rgb max/mean |diff|, depth mean |diff| (world units), "
        "m max: slot_probs max |diff|; RSS: peak of a fresh process running 3 steps."
    )
    return "\n".join(lines)


def _write_json_atomic(path: Path, data: dict[str, Any]) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = mkstemp_beside(path)  # mode 0o666 & ~umask, not mkstemp's 0600
    try:
        with os.fdopen(fd, "w") as f:
            json.dump(data, f, indent=2)
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        prog="python -m benchmark.tools.speedbench",
        description=doc_summary(__doc__),
        formatter_class=DefaultsFormatter,
    )
    ap.add_argument("--scale", default="cpu", choices=["smoke", "cpu", "paper"])
    ap.add_argument("--scenes", type=int, default=4, help="scenes per step (B)")
    ap.add_argument("--rays", type=int, default=256, help="rays per scene (R)")
    ap.add_argument("--repeats", type=int, default=7, help="interleaved timed repeats")
    ap.add_argument("--warmup", type=int, default=2)
    ap.add_argument(
        "--block",
        type=int,
        default=1,
        help="training steps each variant runs in a row per round (times are per step)",
    )
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument(
        "--sharpen",
        type=float,
        default=8.0,
        help="logit scale of the sharp-m variants (1 = leave them out)",
    )
    ap.add_argument("--only", default="", help="comma-separated variant names to run")
    ap.add_argument(
        "--recipe",
        action="store_true",
        help="time the cpu recipe's model: its model levers (benchmark.tools.recipe.RECIPE_LEVERS: "
        "slot locality, foreground box, ...) under every variant",
    )
    ap.add_argument(
        "--weights",
        type=Path,
        default=None,
        metavar="RUN",
        help="start every variant from this training run's weights (its moving average where "
        "it has one) instead of a fresh initialisation",
    )
    ap.add_argument("--no-rss", action="store_true", help="skip the per-variant RSS subprocesses")
    ap.add_argument(
        "--optimizer",
        action="store_true",
        help="instead of the variants: time a whole training step with the training loop's "
        "fused Adam against per-tensor Adam (the scale's default model, --recipe applies)",
    )
    ap.add_argument("--json", type=Path, default=None, help="also write the report here")
    ap.add_argument("--_rss-worker", dest="rss_worker", default=None, help=argparse.SUPPRESS)
    a = ap.parse_args(argv)
    if a.rss_worker is not None:
        _rss_worker(a.rss_worker)
        return 0
    for name in ("scenes", "rays", "repeats", "threads", "block"):
        if getattr(a, name) < 1:
            ap.error(f"--{name} must be >= 1, got {getattr(a, name)}")
    variants = default_variants(a.scale, a.sharpen)
    if a.recipe:
        from benchmark.tools.recipe import recipe_model_levers

        levers = recipe_model_levers()
        for v in variants:  # a variant's own knob settings win over the recipe's
            v.overrides = {**levers, **v.overrides}
    if a.optimizer:
        default = next(v for v in variants if v.name == "default")
        opt_report = optimizer_run(
            a.scale,
            overrides=default.overrides,
            scenes=a.scenes,
            rays=a.rays,
            repeats=a.repeats,
            warmup=a.warmup,
            threads=a.threads,
        )
        a_, b_ = opt_report["forms"]
        print(
            f"per-tensor Adam {a_['steps_per_s']:.2f} steps/s, fused {b_['steps_per_s']:.2f} "
            f"steps/s: {opt_report['ratio']:.3f}x; one update apart by at most "
            f"{opt_report['update_max_abs_diff']:.2e}"
        )
        if a.json is not None:
            _write_json_atomic(a.json, opt_report)
            print(f"wrote {a.json}")
        return 0
    if a.only:
        wanted = [s.strip() for s in a.only.split(",") if s.strip()]
        known = {v.name for v in variants}
        bad = [w for w in wanted if w not in known]
        if bad:
            ap.error(f"--only: unknown variants {bad}; known: {sorted(known)}")
        sharp = {v.sharpen for v in variants if v.name in wanted}
        variants = [v for v in variants if v.name in wanted or (v.reference and v.sharpen in sharp)]
        variants.sort(key=lambda v: not v.reference)  # references first
    report = run(
        a.scale,
        scenes=a.scenes,
        rays=a.rays,
        repeats=a.repeats,
        warmup=a.warmup,
        threads=a.threads,
        sharpen=a.sharpen,
        rss=not a.no_rss,
        variants=variants,
        block=a.block,
        weights=a.weights,
    )
    print(format_table(report))
    if a.json is not None:
        _write_json_atomic(a.json, report)
        print(f"wrote {a.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
