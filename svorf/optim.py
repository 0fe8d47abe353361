"""The optimizer of a training step: Adam and the gradient norm of the NaN guard.

Where this sits: ``svorf.train`` builds its optimizer with :func:`make_optimizer` and
checks every step's gradients with :func:`grad_norm`; ``benchmark.tools.speedbench
--optimizer`` times both against the per-tensor forms they replace.

On a CPU the per-tensor forms took 9.6% of a cpu-recipe training step in a profile (136
parameter tensors): ``torch.optim.Adam`` without ``fused`` loops over the tensors in
Python, and ``clip_grad_norm_(params, inf)`` also multiplies every gradient by 1.0. The
fused kernel applies the same update (up to float rounding) in one call, on CPU and CUDA;
the whole step is 1.049x faster (``speedbench --optimizer``, 2 threads).
"""

from __future__ import annotations

from collections.abc import Iterable

import torch
from torch import Tensor

FUSED_DEVICES = ("cpu", "cuda")
"""Device types with a fused Adam kernel in torch (2.4 and later)."""


def make_optimizer(
    params: Iterable[torch.nn.Parameter],
    lr: float,
    betas: tuple[float, float],
    device: torch.device | str,
    fused: bool | None = None,
) -> torch.optim.Adam:
    """Adam over ``params``; ``fused=None`` uses the fused kernel where the device has one.

    A checkpoint's optimizer state loads into either form (same state tensors); a resumed
    run keeps the form its checkpoint was written with (``param_groups`` carry it).
    """
    if fused is None:
        fused = torch.device(device).type in FUSED_DEVICES
    return torch.optim.Adam(params, lr=lr, betas=betas, fused=fused)


def grad_norm(params: Iterable[torch.nn.Parameter]) -> Tensor:
    """The L2 norm of all gradients together (what ``clip_grad_norm_(params, inf)`` returns,
    without rescaling the gradients); 0 when no parameter has a gradient."""
    grads = [p.grad for p in params if p.grad is not None]
    if not grads:
        return torch.zeros(())
    return torch.nn.utils.get_total_norm(grads, 2.0)
