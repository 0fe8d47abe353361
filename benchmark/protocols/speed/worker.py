"""Subprocess of the ``speed`` protocol: one timed training (+ render) measurement.

Run as ``python -m benchmark.protocols.speed.worker '<json args>'``; prints one
JSON line. A separate process so that its peak memory is this measurement's alone.

Args (JSON object): ``scale``, ``train_preset``, ``variant``, ``seed``, ``device``,
``batch_scenes`` (None = the scale's), ``warmup``, ``steps``, ``train_dir``,
``test_dir``, ``work``, and optionally:

- ``style``: ``"svorf"`` (default: the scale's config, R random rays per scene) or
  ``"uorf"``: the uORF-style configuration of the same code (:func:`uorf_style`):
  every pixel of one target view per scene per step, density-weighted composition,
  slot-conditioned MLP (no hypernetwork); everything else as ``"svorf"``.
- ``render``: also time novel-view and segmentation rendering (default True).
- ``max_memory_mb``: address-space limit (``RLIMIT_AS``) of this process, so that a
  configuration too large for the machine fails here (reported as ``error``) instead
  of pushing other processes into the out-of-memory killer.

Memory: ``peak_memory_mb`` (CPU: peak RSS of this process; CUDA:
``max_memory_allocated`` over the timed steps) and ``train_memory_mb``, that peak minus
the memory in use when the first training step starts (dataset, model and optimizer
built; recorded by a global module forward pre-hook).

Tensor memory: ``tensor_peak_mb`` / ``tensor_train_mb`` (live tensor bytes: the measure
of the paper's GPU figure). CUDA: ``max_memory_allocated`` (train: null). CPU: after the
timed steps, ``tensor_memory_steps`` (default 2) more untimed steps run under
``torch.profiler`` with ``profile_memory=True`` and the running sum of its allocator events
gives the peak (:func:`tensor_memory_curve`); 0 skips it (both null).

Step times: the timed steps' own durations from svorf's ``log.jsonl`` (``log_every=1``:
``1 / steps_per_s`` of each line; data sampling, forward, backward and the optimizer
step, checkpoint writes excluded), so the protocol can take a median.
"""

from __future__ import annotations

import json
import resource
import shutil
import statistics
import sys
import time
from pathlib import Path
from typing import Any

#: Name under which the full-image strategy is registered in svorf's ray-sampling registry
#: (only inside this worker process, for the uORF-style configuration).
FULL_IMAGE = "full_image"

#: ModelConfig overrides that turn sVORF into the uORF-style configuration of the same code.
UORF_MODEL_OVERRIDES: dict[str, Any] = {"composition": "density_weighted", "hypernetwork": False}


def full_image_rays(target_rgb: Any, n: int, generator: Any) -> Any:
    """Ray-sampling strategy: every pixel of one target view (uORF's full-image rendering).

    Args:
        target_rgb: [Vt, H, W, 3] the candidate target views of one scene.
        n: rays to draw; must be ``H * W``.
        generator: torch generator (picks the view uniformly).

    Returns:
        int64 [H * W] flat indices ``v * H * W + pixel`` into the stacked views.

    Raises:
        ValueError: ``n != H * W``.
    """
    import torch

    vt, h, w = int(target_rgb.shape[0]), int(target_rgb.shape[1]), int(target_rgb.shape[2])
    if n != h * w:
        raise ValueError(f"full_image_rays: rays_per_scene must be H*W = {h * w}, got {n}")
    v = int(torch.randint(0, vt, (1,), generator=generator))
    return v * h * w + torch.arange(h * w, dtype=torch.long)


def uorf_style(mcfg: Any, tcfg: Any) -> tuple[Any, Any]:
    """(model, train) configs of the uORF-style configuration of the same code.

    Full-image rendering (``rays_per_scene = image_size**2``, one whole target view per
    scene: registers :data:`FULL_IMAGE` in ``svorf.data``'s registry, in this process),
    density-weighted composition and one slot-conditioned MLP (no hypernetwork). Batch,
    resolution, samples per ray, encoder and decoder are unchanged.
    """
    from svorf.data import RAY_SAMPLING, register_ray_sampling

    if FULL_IMAGE not in RAY_SAMPLING:
        register_ray_sampling(FULL_IMAGE, full_image_rays)
    mcfg = mcfg.replace(**UORF_MODEL_OVERRIDES)
    return mcfg, tcfg.replace(rays_per_scene=int(mcfg.image_size) ** 2, ray_sampling=FULL_IMAGE)


def _rss_mb() -> float:
    """Current resident set size (MiB) from /proc (0 where there is none)."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return float(line.split()[1]) / 1024.0
    except OSError:
        pass
    return 0.0


class _FirstStepMemory:
    """Memory in use when the first training step starts (a global forward pre-hook).

    The first module forward of the process is the model's first training step: the
    dataset, model and optimizer exist by then, the step's activations do not yet.
    CPU: resident set size (MiB); CUDA: ``torch.cuda.memory_allocated`` (MiB).
    """

    def __init__(self, cuda: bool) -> None:
        import torch

        self.cuda = cuda
        self.mb: float | None = None
        self._handle = torch.nn.modules.module.register_module_forward_pre_hook(self._hook)

    def _hook(self, module: Any, args: Any) -> None:
        import torch

        if self.mb is None:
            self.mb = torch.cuda.memory_allocated() / 2**20 if self.cuda else _rss_mb()
            self._handle.remove()


class _FirstForwardTime:
    """Wall-clock time (``time.time_ns``) of the first module forward after construction."""

    def __init__(self) -> None:
        import torch

        self.ns: int | None = None
        self._handle = torch.nn.modules.module.register_module_forward_pre_hook(self._hook)

    def _hook(self, module: Any, args: Any) -> None:
        if self.ns is None:
            self.ns = time.time_ns()
            self._handle.remove()


def tensor_memory_curve(events: list[tuple[int, int]], start_ns: int | None) -> dict[str, float]:
    """Peak live tensor memory from allocator events (the profiler's ``[memory]`` events).

    Args:
        events: ``(time_ns, nbytes)`` pairs, nbytes > 0 for an allocation, < 0 for a free,
            in any order.
        start_ns: when the first training step began (None: the first event).

    Returns:
        ``tensor_peak_mb``: the largest sum of live bytes (MiB, counted from the first
        event: everything the call allocates, so model, optimizer state, data batches and
        activations) from the moment the first step began on (the set-up before it, such
        as reading a checkpoint, is not training); ``tensor_train_mb``: that peak minus the
        sum when the first step began (what the steps add).
    """
    live = 0
    at_start: int | None = None if start_ns is not None else 0
    peak = 0
    for t, nb in sorted(events):
        if at_start is None and t >= start_ns:  # type: ignore[operator]
            at_start = peak = live
        live += nb
        if at_start is not None:
            peak = max(peak, live)
    if at_start is None:  # nothing happened after the start
        at_start = peak = live
    mib = float(2**20)
    return {"tensor_peak_mb": peak / mib, "tensor_train_mb": max(0, peak - at_start) / mib}


def _profiled_tensor_memory(
    adapter: Any, train_dir: str, work: Path, mcfg: Any, tcfg: Any
) -> dict[str, float]:
    """Live tensor memory of a resumed training call on the CPU (torch profiler events).

    The CPU has no ``max_memory_allocated``: this is its analogue. ``torch.profiler`` with
    ``profile_memory=True`` records every allocation and free of the c10 CPU allocator
    (tensors only: not Python, not the libraries, not numpy arrays); the running sum of
    those events over the call, and its rise after the first step began, are what
    :func:`tensor_memory_curve` returns. Profiling slows the steps, so these steps are
    not timed.
    """
    from torch.autograd import DeviceType
    from torch.profiler import ProfilerActivity, profile

    first = _FirstForwardTime()
    with profile(activities=[ProfilerActivity.CPU], profile_memory=True) as prof:
        adapter.train(train_dir, work, mcfg, tcfg, progress=False)
    events = [
        (int(e.start_ns()), int(e.nbytes()))
        for e in prof.profiler.kineto_results.events()
        if e.name() == "[memory]" and e.device_type() == DeviceType.CPU
    ]
    return tensor_memory_curve(events, first.ns)


def _step_times(log: Path, after_step: int) -> list[float]:
    """Seconds of each logged step after ``after_step`` (``log_every=1``)."""
    out = []
    for line in log.read_text().splitlines():
        row = json.loads(line)
        if row["step"] > after_step and row.get("steps_per_s"):
            out.append(1.0 / float(row["steps_per_s"]))
    return out


def _render(adapter: Any, model: Any, ds: Any, cuda: bool, repeats: int) -> dict[str, Any]:
    """Novel-view (every view, one encode) and segmentation (input view) render times."""
    import torch

    def timed(fn: Any) -> float:
        if cuda:
            torch.cuda.synchronize()
        t0 = time.perf_counter()
        fn()
        if cuda:
            torch.cuda.synchronize()
        return time.perf_counter() - t0

    adapter.predict_scene(model, ds, 0)  # untimed (lazy init, caches)
    scenes = [i % len(ds) for i in range(repeats)]
    n_views = ds.n_views
    all_views = [timed(lambda i=i: adapter.predict_scene(model, ds, i)) for i in scenes]
    seg = [
        timed(lambda i=i: adapter.predict_scene(model, ds, i, input_view_only=True)) for i in scenes
    ]
    all_med, seg_med = statistics.median(all_views), statistics.median(seg)
    return {
        "render_wall_s": sum(all_views) + sum(seg),
        "render_s_per_view": all_med / n_views,
        "render_views": n_views,
        "render_repeats": len(scenes),
        "nvs_images_per_s": n_views / all_med,
        "seg_s_per_image": seg_med,
        "seg_images_per_s": 1.0 / seg_med,
    }


def main(argv: list[str]) -> int:
    a = json.loads(argv[0])
    if a.get("max_memory_mb"):
        lim = int(float(a["max_memory_mb"]) * 2**20)
        resource.setrlimit(resource.RLIMIT_AS, (lim, lim))

    import torch

    from benchmark import adapter

    style = a.get("style", "svorf")
    if style not in ("svorf", "uorf"):
        raise ValueError(f"speed worker: style must be 'svorf' or 'uorf', got {style!r}")
    work = Path(a["work"])
    shutil.rmtree(work, ignore_errors=True)  # always a fresh run: timings, not results
    mcfg = adapter.model_config(a["scale"], a["train_preset"], a["variant"])
    warm = adapter.train_config(
        a["scale"], a["train_preset"], a["variant"], a["seed"], a["device"], steps=a["warmup"]
    )
    changes: dict[str, Any] = {"log_every": 1, "ckpt_every": 10**9}
    if a["batch_scenes"]:
        changes["batch_scenes"] = int(a["batch_scenes"])
    warm = warm.replace(**changes)
    if style == "uorf":
        mcfg, warm = uorf_style(mcfg, warm)
    cuda = a["device"].startswith("cuda")
    rss_before = _rss_mb()
    first_step = _FirstStepMemory(cuda)
    timed = warm.replace(steps=a["warmup"] + a["steps"])
    try:
        t0 = time.perf_counter()
        adapter.train(a["train_dir"], work, mcfg, warm, progress=False)
        warm_wall = time.perf_counter() - t0
        if cuda:
            torch.cuda.synchronize()
            torch.cuda.reset_peak_memory_stats()
        t0 = time.perf_counter()
        summary = adapter.train(a["train_dir"], work, mcfg, timed, progress=False)
        if cuda:
            torch.cuda.synchronize()
        timed_wall = time.perf_counter() - t0
    except (MemoryError, RuntimeError) as e:  # RLIMIT_AS reached: torch raises RuntimeError
        msg = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
        oom = isinstance(e, MemoryError) or "alloc" in msg.lower() or "memory" in msg.lower()
        shutil.rmtree(work, ignore_errors=True)
        if not oom:
            raise
        print(json.dumps({"error": "out_of_memory", "message": msg[:300], "style": style}))
        return 0
    s_per_step = summary.get("s_per_step") or timed_wall / a["steps"]
    steps = _step_times(work / "log.jsonl", int(a["warmup"]))
    tensor: dict[str, Any] = {"tensor_peak_mb": None, "tensor_train_mb": None}
    if cuda:
        peak_mb = torch.cuda.max_memory_allocated() / 2**20
        kind = "torch.cuda.max_memory_allocated during the timed steps"
        tensor = {"tensor_peak_mb": peak_mb, "tensor_train_mb": None}
        tensor_kind = kind
    else:
        peak_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
        kind = "peak RSS of the measuring process (CPU)"
        tensor_kind = "not measured (tensor_memory_steps = 0)"
        n_prof = int(a.get("tensor_memory_steps", 2))
        if n_prof > 0:
            prof_cfg = timed.replace(steps=int(timed.steps) + n_prof)
            tensor = _profiled_tensor_memory(adapter, a["train_dir"], work, mcfg, prof_cfg)
            tensor_kind = (
                f"live tensor bytes of the CPU allocator (torch.profiler memory events) over "
                f"a resumed training call of {n_prof} untimed step(s): the CPU analogue of "
                "torch.cuda.max_memory_allocated"
            )
    out: dict[str, Any] = {
        "style": style,
        "s_per_step": float(s_per_step),
        "step_times_s": [round(t, 6) for t in steps],
        "step_time_median_s": statistics.median(steps) if steps else float(s_per_step),
        "timed_steps": int(a["steps"]),
        "warmup_steps": int(a["warmup"]),
        "timed_wall_s": timed_wall,
        "warmup_wall_s": warm_wall,
        "peak_memory_mb": float(peak_mb),
        "rss_before_train_mb": rss_before,
        "memory_at_first_step_mb": first_step.mb,
        "train_memory_mb": None if first_step.mb is None else max(0.0, peak_mb - first_step.mb),
        "memory_kind": kind,
        **tensor,
        "tensor_memory_kind": tensor_kind,
        "batch_scenes": int(timed.batch_scenes),
        "rays_per_scene": int(timed.rays_per_scene),
        "ray_sampling": timed.ray_sampling,
        "params": summary.get("params"),
        "device": a["device"],
        "model_config": adapter.config_dict(mcfg),
        "train_config": adapter.config_dict(timed),
        "render_wall_s": 0.0,
    }
    if a.get("render", True):
        model = adapter.load_model(work, device=a["device"])
        ds = adapter.open_dataset(a["test_dir"], image_size=mcfg.image_size)
        out.update(_render(adapter, model, ds, cuda, int(a.get("render_repeats", 1))))
    shutil.rmtree(work, ignore_errors=True)
    print(json.dumps(out))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
