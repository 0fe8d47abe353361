"""Data-parallel training under ``torchrun`` (DDP semantics, exact to single-process).

Where this sits: ``svorf train`` (``svorf.cli``) calls :func:`init_from_env` when it
runs under ``torchrun``; :func:`svorf.train.train` then finds the process group with
:func:`current` and uses the helpers below. Nothing else in ``svorf`` touches
``torch.distributed``; a single process never initialises it.

How a step is split across W ranks (global batch B = ``TrainConfig.batch_scenes``,
per-rank batch b = B / W, an error unless W divides B):

- Every rank is seeded identically and draws the *whole* global batch (scenes, input
  views, rays) from the shared data generator, then keeps its rows ``[r*b, (r+1)*b)``:
  a DistributedSampler over scenes whose draws are the single-process draws. Drawing B
  scenes' indices on every rank is cheap (the rays are cached in memory).
- The model's own randomness (stratified jitter, fine-sample quantiles, the packed-11
  slot mask) is drawn at the global batch size too and sliced per rank
  (:class:`GlobalBatchRandom`), so every rank's random state stays equal to the
  single-process state and checkpoints carry the same RNG state.
- Gradients of the per-rank mean losses are averaged across ranks
  (:func:`average_gradients`); equal per-rank batches make that the gradient of the
  global mean loss. Loss statistics are averaged the same way for logging.

So W ranks train the same model as one process with the same global batch, up to
floating-point summation order (``tests/test_distributed.py`` checks 2 CPU ranks against
one process). One exception: BatchNorm (``ModelConfig.enc_norm="batch"``) is converted
to SyncBatchNorm on CUDA; PyTorch's SyncBatchNorm has no CPU kernel, so on CPU each rank
normalises with its own b scenes' statistics (a warning says so).

Rank 0 alone writes the checkpoint, logs, ``config.json``/``summary.json``, runs the
held-out evaluation and shows the progress bar; every rank reads the same run folder on
resume, so multi-node runs need a shared file system for ``--out``.

Backends: NCCL when the device is CUDA, gloo on CPU. Each rank uses ``cuda:LOCAL_RANK``
when the configured device is "auto" or "cuda".
"""

from __future__ import annotations

import datetime
import os
import warnings
from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor, nn
from torch.overrides import TorchFunctionMode

__all__ = [
    "DistContext",
    "GlobalBatchRandom",
    "all_reduce_max",
    "average_gradients",
    "broadcast_module",
    "current",
    "env_world_size",
    "init_from_env",
    "local_batch",
    "local_device",
    "prepare_model",
    "shutdown",
]

#: Environment variable with the collective timeout in minutes (rank 0 evaluates and
#: writes checkpoints while the other ranks wait in the next step's all-reduce).
TIMEOUT_ENV = "SVORF_DIST_TIMEOUT_MIN"


@dataclass(frozen=True)
class DistContext:
    """This process's place in the process group.

    Attributes:
        rank: global rank in ``[0, world_size)``.
        world_size: number of ranks (W >= 2; a single process has no context).
        local_rank: rank on this node (selects ``cuda:local_rank``).
        backend: "gloo" or "nccl".
    """

    rank: int
    world_size: int
    local_rank: int
    backend: str

    @property
    def is_main(self) -> bool:
        """True on rank 0 (the rank that writes files and logs)."""
        return self.rank == 0


def env_world_size() -> int:
    """``WORLD_SIZE`` as set by ``torchrun`` (1 when not set).

    Raises:
        ValueError: ``WORLD_SIZE`` is set but not a positive integer.
    """
    raw = os.environ.get("WORLD_SIZE", "1")
    try:
        w = int(raw)
    except ValueError:
        w = 0
    if w < 1:
        raise ValueError(f"WORLD_SIZE must be a positive integer (set by torchrun), got {raw!r}")
    return w


def _env_int(name: str) -> int:
    raw = os.environ.get(name)
    if raw is None:
        raise ValueError(
            f"WORLD_SIZE is set but {name} is not: launch with `torchrun --nproc_per_node N "
            f"-m svorf.cli train ...` (or set RANK, LOCAL_RANK, MASTER_ADDR, MASTER_PORT)"
        )
    try:
        return int(raw)
    except ValueError:
        raise ValueError(f"{name} must be an integer (set by torchrun), got {raw!r}") from None


def init_from_env(device: str = "auto") -> DistContext | None:
    """Initialise the default process group from ``torchrun``'s environment variables.

    Does nothing and returns None for a single process (``WORLD_SIZE`` unset or 1), so
    ``svorf train`` behaves exactly as before outside ``torchrun``. Under ``torchrun``
    the backend is NCCL if ``device`` resolves to CUDA, else gloo.

    Args:
        device: ``TrainConfig.device`` ("auto", "cpu", "cuda", "cuda:N").

    Returns:
        The context, or None for a single process.

    Raises:
        ValueError: an incomplete or invalid torchrun environment (one line).
    """
    world = env_world_size()
    if world == 1:
        return None
    import torch.distributed as dist

    if not dist.is_available():  # pragma: no cover - every Linux/macOS wheel has it
        raise ValueError("this PyTorch build has no torch.distributed; cannot run under torchrun")
    rank, local_rank = _env_int("RANK"), _env_int("LOCAL_RANK")
    if not 0 <= rank < world:
        raise ValueError(f"RANK must be in [0, WORLD_SIZE={world}), got {rank}")
    if dist.is_initialized():
        return current()
    use_cuda = _wants_cuda(device)
    backend = "nccl" if use_cuda else "gloo"
    if use_cuda:
        torch.cuda.set_device(local_rank)
    minutes = float(os.environ.get(TIMEOUT_ENV, "30"))
    dist.init_process_group(
        backend=backend,
        rank=rank,
        world_size=world,
        timeout=datetime.timedelta(minutes=minutes),
    )
    return DistContext(rank, world, local_rank, backend)


def _wants_cuda(device: str) -> bool:
    if device == "auto":
        return torch.cuda.is_available()
    return torch.device(device).type == "cuda"


def current() -> DistContext | None:
    """The active process group as a context, or None (no group, or a group of one)."""
    import torch.distributed as dist

    if not (dist.is_available() and dist.is_initialized()):
        return None
    world = dist.get_world_size()
    if world < 2:
        return None
    local = int(os.environ.get("LOCAL_RANK", dist.get_rank()))
    return DistContext(dist.get_rank(), world, local, str(dist.get_backend()))


def shutdown(synchronise: bool = True) -> None:
    """Destroy the default process group if one exists (end of ``svorf train``).

    Args:
        synchronise: wait at a barrier first, so that no rank closes its connections
            while a peer is still working (rank 0 writes the checkpoint and evaluates
            after the last step). Without it, gloo can abort the rank that leaves first
            ("terminate called without an active exception"). Pass False after an
            error: a peer that died would leave the barrier waiting for the timeout.
    """
    import torch.distributed as dist

    if dist.is_available() and dist.is_initialized():
        if synchronise and dist.get_world_size() > 1:
            dist.barrier()
        dist.destroy_process_group()


def local_batch(batch_scenes: int, world_size: int) -> int:
    """Per-rank batch b = B / W.

    Raises:
        ValueError: W does not divide B (the global batch must equal ``batch_scenes``).
    """
    if batch_scenes % world_size:
        raise ValueError(
            f"TrainConfig.batch_scenes={batch_scenes} is not divisible by the world size "
            f"{world_size} (torchrun ranks); each rank trains on batch_scenes / world_size "
            f"scenes, so choose a batch that is a multiple of {world_size}"
        )
    return batch_scenes // world_size


def local_device(ctx: DistContext, device: torch.device) -> torch.device:
    """The device of this rank: ``cuda:local_rank`` for an unindexed CUDA device.

    An explicit index (``cuda:N``) is kept (the user placed the ranks themselves).
    """
    if device.type == "cuda" and device.index is None:
        return torch.device("cuda", ctx.local_rank)
    return device


def prepare_model(model: nn.Module, device: torch.device, ctx: DistContext) -> nn.Module:
    """BatchNorm -> SyncBatchNorm on CUDA (same statistics as the global batch).

    On CPU, PyTorch's SyncBatchNorm has no kernel: BatchNorm layers stay per-rank and a
    warning (rank 0) says that the run then differs from a single-process one. The state
    dict keys are unchanged either way, so checkpoints load into a plain model.
    """
    has_bn = any(isinstance(m, nn.modules.batchnorm._BatchNorm) for m in model.modules())
    if not has_bn:
        return model
    if device.type == "cuda":
        return nn.SyncBatchNorm.convert_sync_batchnorm(model)
    if ctx.is_main:
        warnings.warn(
            "svorf train under torchrun on CPU: BatchNorm statistics are per rank "
            "(SyncBatchNorm needs CUDA), so results differ from a single-process run; "
            "use a config with enc_norm='group' for exact equivalence",
            stacklevel=2,
        )
    return model


@torch.no_grad()
def broadcast_module(module: nn.Module, src: int = 0) -> None:
    """Copy every parameter and buffer of rank ``src`` to all ranks (in place)."""
    import torch.distributed as dist

    for t in list(module.parameters()) + list(module.buffers()):
        dist.broadcast(t.data, src=src)


@torch.no_grad()
def average_gradients(params: list[nn.Parameter], stats: Tensor, world_size: int) -> Tensor:
    """Average gradients and loss statistics over the ranks in one all-reduce.

    A parameter gets a gradient if any rank produced one (the others contribute zeros)
    and keeps ``grad=None`` if no rank did, as in a single process (Adam skips those).

    Args:
        params: the model parameters, in the same order on every rank.
        stats: [S] float tensor of per-rank scalars (loss parts) to average.
        world_size: W.

    Returns:
        mean_stats [S]; the gradients are replaced in place by their mean.
    """
    import torch.distributed as dist

    dtype = next((p.grad.dtype for p in params if p.grad is not None), torch.float32)
    device = stats.device if not params else params[0].device
    present = torch.tensor(
        [p.grad is not None for p in params], dtype=dtype, device=device
    )  # [P] 1/0
    grads = [
        p.grad.reshape(-1).to(dtype) if p.grad is not None else p.new_zeros(p.numel(), dtype=dtype)
        for p in params
    ]
    flat = torch.cat([present, stats.to(device=device, dtype=dtype).reshape(-1), *grads])
    dist.all_reduce(flat, op=dist.ReduceOp.SUM)
    n_p, n_s = len(params), stats.numel()
    any_grad = flat[:n_p] > 0
    mean_stats = flat[n_p : n_p + n_s] / world_size
    offset = n_p + n_s
    for i, p in enumerate(params):
        n = p.numel()
        if any_grad[i]:
            g = (flat[offset : offset + n] / world_size).view_as(p).to(p.dtype)
            if p.grad is None:
                p.grad = g.clone()
            else:
                p.grad.copy_(g)
        offset += n
    return mean_stats.to(stats.dtype)


def all_reduce_max(value: float, device: torch.device) -> float:
    """The maximum of a float over the ranks (e.g. the wall clock, so all stop together)."""
    import torch.distributed as dist

    t = torch.tensor([value], dtype=torch.float64, device=device)
    dist.all_reduce(t, op=dist.ReduceOp.MAX)
    return float(t.item())


#: Random factory functions whose first size argument is the batch (sliced per rank).
_SLICED = frozenset((torch.rand, torch.randn))
#: Random functions a training forward must not call under DDP (no batch axis to slice).
_UNSLICEABLE = frozenset(
    (
        torch.randint,
        torch.randperm,
        torch.rand_like,
        torch.randn_like,
        torch.randint_like,
        torch.bernoulli,
        torch.multinomial,
        torch.normal,
        torch.poisson,
        torch.nn.functional.dropout,
        Tensor.uniform_,
        Tensor.normal_,
        Tensor.bernoulli_,
        Tensor.random_,
        Tensor.exponential_,
    )
)


class GlobalBatchRandom(TorchFunctionMode):
    """Inside the context, batch-leading random draws happen at the global batch size.

    ``torch.rand(b, ...)`` / ``torch.randn(b, ...)`` with b = the per-rank batch draw
    ``[B, ...]`` from the same generator (B = ``world_size * b``) and return this rank's
    rows ``[rank*b, (rank+1)*b)``. With every rank seeded alike, each rank sees exactly
    the numbers a single process would draw for its scenes, and all ranks' generators stay
    equal. Draws without a batch-leading size, and random ops that cannot be sliced this
    way, raise ``RuntimeError`` rather than silently diverge from single-process training.

    Args:
        rank: this rank; world_size: W; local_batch: b.

    Example:
        >>> with GlobalBatchRandom(rank=1, world_size=2, local_batch=1):  # doctest: +SKIP
        ...     u = torch.rand(1, 64, 8)  # rows [1:2] of torch.rand(2, 64, 8)
    """

    def __init__(self, rank: int, world_size: int, local_batch: int) -> None:
        super().__init__()
        self.rank, self.world_size, self.local_batch = rank, world_size, local_batch

    def __torch_function__(self, func, types, args=(), kwargs=None):
        kwargs = dict(kwargs or {})
        if func in _SLICED:
            size, rest = _split_size(args, kwargs)
            if not size or size[0] != self.local_batch:
                raise RuntimeError(
                    f"{func.__name__}{tuple(size)} inside a training forward under torchrun: "
                    f"model randomness must be drawn with the batch ({self.local_batch} "
                    f"scenes per rank) as the first dimension to match single-process runs"
                )
            full = (self.local_batch * self.world_size, *size[1:])
            out = func(full, *rest, **kwargs)
            lo = self.rank * self.local_batch
            return out[lo : lo + self.local_batch]
        if func in _UNSLICEABLE and not _is_noop_dropout(func, args, kwargs):
            raise RuntimeError(
                f"{getattr(func, '__name__', func)} inside a training forward under torchrun "
                f"cannot be matched to single-process draws; draw it with torch.rand(batch, ...)"
            )
        return func(*args, **kwargs)


def _split_size(args: tuple, kwargs: dict[str, Any]) -> tuple[tuple[int, ...], tuple]:
    """``torch.rand``'s size (varargs ints, one sequence, or ``size=``) and the rest."""
    if "size" in kwargs:
        return tuple(int(s) for s in kwargs.pop("size")), tuple(args)
    if args and isinstance(args[0], (tuple, list, torch.Size)):
        return tuple(int(s) for s in args[0]), tuple(args[1:])
    n = 0
    while n < len(args) and isinstance(args[n], int):
        n += 1
    return tuple(int(s) for s in args[:n]), tuple(args[n:])


def _is_noop_dropout(func, args: tuple, kwargs: dict[str, Any]) -> bool:
    if func is not torch.nn.functional.dropout:
        return False
    p = kwargs.get("p", args[1] if len(args) > 1 else 0.5)
    training = kwargs.get("training", args[2] if len(args) > 2 else True)
    return float(p) == 0.0 or not training
