"""Float64 oracles and helpers of the ``stability`` protocol.

Where this sits: :mod:`benchmark.protocols.stability` (the volume renderer's stress cases)
and :mod:`benchmark.protocols.stability.cases` (composition, losses, metrics) both score
against these references and draw their inputs and NaN/Inf counts with these helpers;
neither module imports the other's internals.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

__all__ = ["loguniform", "nonfinite_count", "reference_render", "reference_weights"]


def reference_weights(sigma: Tensor, delta: Tensor) -> Tensor:
    """Quadrature weights ``T_i (1 - exp(-sigma_i delta_i))`` in float64 along the last axis,
    without clamping; an interval of length 0 contributes nothing whatever its density
    (``0 * inf`` is taken as 0)."""
    s = sigma.double().clamp_min(0.0)
    delta = delta.double()
    tau = torch.where(delta > 0, s * delta, torch.zeros_like(s))
    excl = torch.cat([torch.zeros_like(tau[..., :1]), torch.cumsum(tau, -1)[..., :-1]], -1)
    return torch.exp(-excl) * -torch.expm1(-tau)  # exp(-inf) = 0; tau = inf -> alpha 1


def reference_render(sigma: Tensor, rgb: Tensor, t: Tensor, last_delta: float) -> dict[str, Tensor]:
    """Exact NeRF quadrature in float64 (the oracle).

    ``w_i = T_i (1 - exp(-sigma_i delta_i))``, ``T_i = exp(-sum_{j<i} sigma_j delta_j)``,
    ``delta_i = t_{i+1} - t_i`` and ``delta_N = last_delta``; an interval of length 0
    contributes nothing whatever its density (``0 * inf`` is taken as 0).

    Args:
        sigma: [R, N] densities (may hold inf).
        rgb: [R, N, 3].
        t: [R, N] sorted distances.
        last_delta: length of the last interval.

    Returns:
        ``{"rgb" [R, 3], "depth" [R], "acc" [R], "weights" [R, N]}``, float64.
    """
    t64 = t.double()
    delta = torch.cat(
        [t64[:, 1:] - t64[:, :-1], torch.full_like(t64[:, :1], float(last_delta))], 1
    ).clamp_min(0)
    w = reference_weights(sigma, delta)
    return {
        "rgb": (w[..., None] * rgb.double()).sum(1),
        "depth": (w * t64).sum(1),
        "acc": w.sum(1),
        "weights": w,
    }


def loguniform(gen: torch.Generator, shape: tuple[int, ...], lo: float, hi: float) -> Tensor:
    """float64 samples of ``shape``, log-uniform in ``[lo, hi]`` (drawn from ``gen``)."""
    u = torch.rand(*shape, generator=gen, dtype=torch.float64)
    return torch.exp(math.log(lo) + u * (math.log(hi) - math.log(lo)))


def nonfinite_count(x: Tensor | None) -> int:
    """Number of NaN / Inf entries of ``x`` (0 for None, e.g. a missing gradient)."""
    return 0 if x is None else int((~torch.isfinite(x.float())).sum())
