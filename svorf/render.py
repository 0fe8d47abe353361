"""Ray sampling and volume rendering; knows nothing of slots.

Where it sits: ``SVORF.render_rays`` draws samples (:func:`sample_stratified`,
:func:`sample_pdf`), optionally clips rays to the scene box (:func:`clip_rays_to_box`),
queries the composed field, and integrates it with :func:`volume_render`.

Conventions: ``t`` is the distance along the ray ``o + t d``; with unit-norm ``d`` (what the
model expects) it is the Euclidean distance from the ray origin (not the planar camera z).
Samples are sorted along the last axis. Rendering runs in float32 even under autocast, with
the transmittance accumulated in log space (an exclusive cumulative sum of sigma * delta).
"""

from __future__ import annotations

import torch
from torch import Tensor

#: Densities are clamped to this before multiplying by interval lengths (1e10 for the last
#: one), so sigma * delta stays finite in float32 (<= 1e20 << 3.4e38), even for sigma = inf.
#: Every transmittance computed from densities (here and in ``svorf.model``) uses it.
SIGMA_GUARD = 1e10


def render_weights(sigma: Tensor, delta: Tensor) -> Tensor:
    """NeRF quadrature weights w_i = T_i (1 - exp(-sigma_i delta_i)), float32.

    Args:
        sigma: [..., N] densities (>= 0; negatives are treated as 0).
        delta: [..., N] interval lengths (>= 0).
    Returns:
        weights [..., N], float32; T_i = exp(-sum_{j<i} sigma_j delta_j) in log space.
    """
    with torch.autocast(device_type=sigma.device.type, enabled=False):
        sigma = sigma.float().clamp(0.0, SIGMA_GUARD)
        tau = sigma * delta.float().clamp_min(0.0)  # optical thickness per interval
        log_t = -torch.cumsum(tau, dim=-1)
        log_t = torch.cat([torch.zeros_like(log_t[..., :1]), log_t[..., :-1]], dim=-1)
        alpha = -torch.expm1(-tau)
        return torch.exp(log_t) * alpha


def intervals(t: Tensor, last_delta: float | Tensor) -> Tensor:
    """delta_i = t_{i+1} - t_i, with delta_N = ``last_delta`` (float or [...] tensor)."""
    t = t.float()
    last = torch.as_tensor(last_delta, dtype=t.dtype, device=t.device)
    if last.dim() > 0:
        last = last[..., None]
    last = last.expand(t[..., :1].shape)
    return torch.cat([t[..., 1:] - t[..., :-1], last], dim=-1).clamp_min(0.0)


def volume_render(
    sigma: Tensor, rgb: Tensor, t: Tensor, *, last_delta: float | Tensor = 1e10
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Integrate a field along rays (paper eq. 2).

    Args:
        sigma: [..., N] densities (1/world unit).
        rgb: [..., N, 3] colours.
        t: [..., N] sorted sample distances along the rays.
        last_delta: length of the last interval. The default 1e10 is "infinite" (NeRF): the
            last sample absorbs what the ray has left. Pass ``far - t[..., -1]`` ([...]) for
            far-bounded rendering.
    Returns:
        rgb [..., 3], depth [...], weights [..., N], acc [...], all float32. ``depth`` is the
        expected termination distance sum_i w_i t_i (NeRF convention, not divided by acc);
        ``acc`` = sum_i w_i is the probability that the ray terminates.

    Example:
        >>> t = torch.linspace(0, 1, 8).expand(2, 8)
        >>> rgb, depth, w, acc = volume_render(torch.ones(2, 8), torch.rand(2, 8, 3), t)
    """
    if sigma.shape != t.shape or rgb.shape[:-1] != t.shape or rgb.shape[-1] != 3:
        raise ValueError(
            "volume_render: expected sigma [..., N], rgb [..., N, 3], t [..., N]; got "
            f"sigma {tuple(sigma.shape)}, rgb {tuple(rgb.shape)}, t {tuple(t.shape)}"
        )
    with torch.autocast(device_type=sigma.device.type, enabled=False):
        weights = render_weights(sigma, intervals(t, last_delta))
        acc = weights.sum(dim=-1)
        depth = (weights * t.float()).sum(dim=-1)
        out = (weights[..., None] * rgb.float()).sum(dim=-2)
    return out, depth, weights, acc


def sample_stratified(
    near: float | Tensor,
    far: float | Tensor,
    R: int,
    N: int,
    perturb: bool,
    *,
    device: torch.device | str | None = None,
    dtype: torch.dtype | None = None,
    generator: torch.Generator | None = None,
) -> Tensor:
    """N stratified samples per ray in [near, far].

    Args:
        near, far: floats or tensors broadcastable to [..., R] (per-ray bounds).
        R: rays; N: samples per ray.
        perturb: uniform jitter inside each of the N equal bins; else bin centres.
        device, dtype: used when near and far are both floats.
    Returns:
        t [..., R, N], sorted, near <= t <= far.
    """
    ref = near if isinstance(near, Tensor) else far if isinstance(far, Tensor) else None
    device = ref.device if ref is not None else device
    dtype = (ref.dtype if ref is not None else dtype) or torch.float32
    near_t = torch.as_tensor(near, device=device, dtype=dtype)
    far_t = torch.as_tensor(far, device=device, dtype=dtype)
    shape = torch.broadcast_shapes(near_t.shape, far_t.shape, (R,))
    near_t, far_t = near_t.expand(shape)[..., None], far_t.expand(shape)[..., None]
    i = torch.arange(N, device=device, dtype=dtype)
    if perturb:
        u = torch.rand(*shape, N, device=device, dtype=dtype, generator=generator)
    else:
        u = torch.full((N,), 0.5, device=device, dtype=dtype)
    frac = (i + u) / N
    return torch.minimum(near_t + (far_t - near_t) * frac, far_t)


def sample_pdf(
    bins: Tensor,
    weights: Tensor,
    N: int,
    det: bool,
    *,
    generator: torch.Generator | None = None,
) -> Tensor:
    """Inverse-transform sampling of a piecewise-constant PDF (NeRF hierarchical sampling).

    Args:
        bins: [..., M+1] sorted bin edges (for sVORF: near, coarse midpoints, far).
        weights: [..., M] non-negative bin weights (detached here; 1e-5 is added to each so
            empty rays sample uniformly).
        N: samples per ray.
        det: evenly spaced quantiles (i + 0.5) / N; else stratified random quantiles.
    Returns:
        t [..., N], sorted, within [bins[..., 0], bins[..., -1]], no gradient.
    """
    if bins.shape[:-1] != weights.shape[:-1] or bins.shape[-1] != weights.shape[-1] + 1:
        raise ValueError(
            "sample_pdf: expected bins [..., M+1] and weights [..., M]; got "
            f"bins {tuple(bins.shape)}, weights {tuple(weights.shape)}"
        )
    bins = bins.detach().float()
    w = weights.detach().float().clamp_min(0.0) + 1e-5
    pdf = w / w.sum(dim=-1, keepdim=True)
    cdf = torch.cumsum(pdf, dim=-1)
    cdf = torch.cat([torch.zeros_like(cdf[..., :1]), cdf], dim=-1).clamp(max=1.0)  # [..., M+1]
    batch = cdf.shape[:-1]
    i = torch.arange(N, device=bins.device, dtype=bins.dtype)
    if det:
        u = ((i + 0.5) / N).expand(*batch, N)
    else:
        u = (i + torch.rand(*batch, N, device=bins.device, generator=generator)) / N
    u = u.contiguous()
    M = weights.shape[-1]
    idx = torch.searchsorted(cdf.contiguous(), u, right=True)
    below = (idx - 1).clamp(0, M)
    above = idx.clamp(0, M)
    cdf_lo, cdf_hi = cdf.gather(-1, below), cdf.gather(-1, above)
    bin_lo, bin_hi = bins.gather(-1, below), bins.gather(-1, above)
    denom = cdf_hi - cdf_lo
    denom = torch.where(denom < 1e-8, torch.ones_like(denom), denom)
    frac = ((u - cdf_lo) / denom).clamp(0.0, 1.0)
    samples = bin_lo + frac * (bin_hi - bin_lo)
    return samples.clamp(bins[..., :1], bins[..., -1:])


def ray_box_intersect(
    rays_o: Tensor, rays_d: Tensor, half: float, z_range: tuple[float, float] | None = None
) -> tuple[Tensor, Tensor, Tensor]:
    """Slab test of rays against the cube [-half, half]^3 (or the box [-half, half]^2 x
    [z_range[0], z_range[1]] when ``z_range`` is given).

    Args:
        rays_o, rays_d: [..., 3] (d need not be unit; components near 0 are guarded).
        z_range: (low, high) z of the box; None: [-half, half].
    Returns:
        t_enter [...], t_exit [...], hit [...] (bool, t_exit > max(t_enter, 0)).
    """
    eps = 1e-9
    d = rays_d.float()
    d = torch.where(d.abs() < eps, torch.where(d < 0, -eps, eps), d)
    inv = 1.0 / d
    o = rays_o.float()
    lo = torch.tensor([-half, -half, -half if z_range is None else z_range[0]], device=o.device)
    hi = torch.tensor([half, half, half if z_range is None else z_range[1]], device=o.device)
    t0 = (lo - o) * inv
    t1 = (hi - o) * inv
    t_enter = torch.minimum(t0, t1).amax(dim=-1)
    t_exit = torch.maximum(t0, t1).amin(dim=-1)
    hit = t_exit > t_enter.clamp_min(0.0)
    return t_enter, t_exit, hit


def clip_rays_to_box(
    rays_o: Tensor,
    rays_d: Tensor,
    near: float,
    far: float,
    half: float,
    z_range: tuple[float, float] | None = None,
    floor_z: float | None = None,
    floor_front: bool = False,
) -> tuple[Tensor, Tensor]:
    """Per-ray [near, far] clipped to the box [-half, half]^3, or to the slab
    [-half, half]^2 x [z_range[0], z_range[1]] when ``z_range`` is given.

    Rays that miss the slab (above the objects towards the horizon) keep the cube's
    interval; rays that miss the cube (or whose clipped interval is empty) keep the full
    [near, far], so every ray still has valid, sorted samples (the background slot then
    colours them). With ``floor_z``, a downward ray whose interval ends before it reaches
    the plane z = ``floor_z`` (it leaves the box through a side wall: floor seen beyond
    the box) is extended to that plane, at most to ``far``, so that the background can put
    the far floor where it is instead of on the box wall. With ``floor_front`` too, a
    downward ray that reaches that plane before it enters the box (floor seen in front of
    or beside the box: the near corners of the image) is sampled from ``near`` to the plane
    instead of inside the box under the floor.

    Returns:
        near_r [...], far_r [...] float32 with near <= near_r < far_r <= far.
    """
    near_r = torch.full(rays_o.shape[:-1], float(near), device=rays_o.device)
    far_r = torch.full(rays_o.shape[:-1], float(far), device=rays_o.device)
    for zr in (None,) if z_range is None else (None, z_range):  # the cube, then the slab
        t_enter, t_exit, hit = ray_box_intersect(rays_o, rays_d, half, zr)
        lo, hi = t_enter.clamp(min=near), t_exit.clamp(max=far)
        ok = hit & (hi > lo + 1e-6)
        near_r, far_r = torch.where(ok, lo, near_r), torch.where(ok, hi, far_r)
    if floor_z is not None:
        dz = rays_d[..., 2].float()
        down = dz < -1e-9
        t_floor = (float(floor_z) - rays_o[..., 2].float()) / torch.where(down, dz, -1.0)
        extend = down & (t_floor > far_r)
        far_r = torch.where(extend, t_floor.clamp(max=float(far)), far_r)
        if floor_front:
            front = down & (t_floor <= near_r) & (t_floor > near + 1e-3)
            near_r = torch.where(front, torch.full_like(near_r, float(near)), near_r)
            far_r = torch.where(front, t_floor, far_r)
    elif floor_front:
        raise ValueError("clip_rays_to_box: floor_front needs floor_z")
    return near_r, far_r
