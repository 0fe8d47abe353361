"""Connectivity regularisation (paper 3.4): Mip-NeRF 360 distortion on each object field.

Also the cpu recipe's optional prices (each a ``ModelConfig`` lever, off at the paper
scale): the same distortion on the composed ray (:func:`ray_distortion`), the object
slots' rendered weight (:func:`object_mass`, :func:`halo_gate`) and their half-transparent
matter (:func:`soft_matter`).

Where it sits: ``SVORF.render_rays`` calls :func:`connectivity_loss` on the fine-pass samples
with every slot's own density sigma_i (not the composed one); ``SVORF.loss`` adds
``connect_lambda`` (0.01) times it to the MSE.

L(t, w) = sum_{i,j} w_i w_j |(t_i + t_{i+1})/2 - (t_j + t_{j+1})/2| + 1/3 sum_i w_i^2 (t_{i+1} - t_i)

The O(N) form uses sorted midpoints: sum_{i,j} w_i w_j |m_i - m_j| =
2 sum_i w_i (m_i W_{<i} - S_{<i}) with W_{<i} = sum_{j<i} w_j and S_{<i} = sum_{j<i} w_j m_j.
"""

from __future__ import annotations

import torch
from torch import Tensor

from .render import SIGMA_GUARD, render_weights, volume_render


def _check(weights: Tensor, edges: Tensor, name: str) -> None:
    if edges.shape[:-1] != weights.shape[:-1] or edges.shape[-1] != weights.shape[-1] + 1:
        raise ValueError(
            f"{name}: expected weights [..., N] and edges [..., N+1]; got weights "
            f"{tuple(weights.shape)}, edges {tuple(edges.shape)}"
        )


def _edges_to_far(t: Tensor, far_r: Tensor) -> Tensor:
    """Interval edges [..., N+1] of sorted samples ``t`` [..., N] whose last interval ends
    at the ray's far bound ``far_r`` [...] (float32; a far bound below t_N is raised to it)."""
    edges = torch.cat([t.float(), far_r.float()[..., None]], dim=-1)
    return torch.maximum(edges, torch.cummax(edges, dim=-1).values)


def distortion_loss(weights: Tensor, edges: Tensor) -> Tensor:
    """Mip-NeRF 360 distortion loss per ray, O(N).

    Args:
        weights: [..., N] interval weights.
        edges: [..., N+1] sorted interval edges (normalised distances; interval i is
            [edges_i, edges_{i+1}]).
    Returns:
        [...] loss per ray, float32.
    """
    _check(weights, edges, "distortion_loss")
    w = weights.float()
    s = edges.float()
    mid = 0.5 * (s[..., 1:] + s[..., :-1])
    width = s[..., 1:] - s[..., :-1]
    w_cum = torch.cumsum(w, dim=-1) - w  # exclusive prefix sums
    wm_cum = torch.cumsum(w * mid, dim=-1) - w * mid
    inter = 2.0 * (w * (mid * w_cum - wm_cum)).sum(dim=-1)
    intra = (w.square() * width).sum(dim=-1) / 3.0
    return inter + intra


def distortion_loss_reference(weights: Tensor, edges: Tensor) -> Tensor:
    """O(N^2) definition of :func:`distortion_loss` (test oracle); works in any dtype."""
    _check(weights, edges, "distortion_loss_reference")
    mid = 0.5 * (edges[..., 1:] + edges[..., :-1])
    width = edges[..., 1:] - edges[..., :-1]
    pair = weights[..., :, None] * weights[..., None, :]
    inter = (pair * (mid[..., :, None] - mid[..., None, :]).abs()).sum(dim=(-1, -2))
    return inter + (weights.square() * width).sum(dim=-1) / 3.0


def connectivity_loss(
    sigma_k: Tensor,
    t: Tensor,
    far_r: Tensor,
    near: float,
    far: float,
    slot_mask: Tensor | None = None,
) -> Tensor:
    """Distortion loss on every object field's own weights, reduced to a scalar.

    Each slot's weights come from its own density alone: w_ik = T_ik (1 - exp(-sigma_ik
    delta_i)). Intervals are [t_i, t_{i+1}] with t_{N+1} = the ray's far bound (a finite last
    interval, unlike the composite rendering's "infinite" one), and distances are normalised
    as (t - near) / (far - near) with the config's global near/far, so the loss has the same
    scale on every ray (the paper's "normalized ray distance").

    Reduction: sum over samples (the formula), mean over rays, mean over the active slots of
    all scenes (masked-off slots excluded; all K slots, background included, otherwise).

    Args:
        sigma_k: [B, K, R, N] per-slot densities at the samples.
        t: [B, R, N] sorted sample distances; far_r: [B, R] per-ray far bound.
        near, far: the config's global bounds for the normalisation.
        slot_mask: [B, K] bool, True = slot active; None = all active.
    Returns:
        scalar float32 tensor.
    """
    B, K, R, N = sigma_k.shape
    if t.shape != (B, R, N) or far_r.shape != (B, R):
        raise ValueError(
            f"connectivity_loss: expected t [B={B}, R={R}, N={N}] and far_r [B, R]; got "
            f"t {tuple(t.shape)}, far_r {tuple(far_r.shape)}"
        )
    edges = _edges_to_far(t, far_r)  # [B, R, N+1]
    delta = (edges[..., 1:] - edges[..., :-1])[:, None]  # [B, 1, R, N]
    w = render_weights(sigma_k, delta)  # [B, K, R, N]
    s = ((edges - near) / (far - near))[:, None].expand(B, K, R, N + 1)
    per_slot = distortion_loss(w, s).mean(dim=-1)  # [B, K]
    if slot_mask is None:
        return per_slot.mean()
    m = slot_mask.to(per_slot.dtype)
    return (per_slot * m).sum() / m.sum().clamp_min(1.0)


def ray_distortion(sigma: Tensor, t: Tensor, far_r: Tensor, near: float, far: float) -> Tensor:
    """Distortion loss on the composed field's weights, mean over rays (scalar float32).

    The same loss and intervals as :func:`connectivity_loss` (last interval ending at the
    ray's far bound, distances normalised by the config's ``far - near``), on the weights
    of the composed density ``sigma`` [B, R, N] at the sorted samples ``t`` [B, R, N] instead
    of each slot's own: a ray whose weight is split between two surfaces (an object's thin
    halo in front of the floor) pays for the gap. ``ModelConfig.ray_distortion`` prices it.
    """
    if t.shape != sigma.shape or far_r.shape != sigma.shape[:-1]:
        raise ValueError(
            f"ray_distortion: expected sigma, t [B, R, N] and far_r [B, R]; got sigma "
            f"{tuple(sigma.shape)}, t {tuple(t.shape)}, far_r {tuple(far_r.shape)}"
        )
    edges = _edges_to_far(t, far_r)
    w = render_weights(sigma, edges[..., 1:] - edges[..., :-1])
    return distortion_loss(w, (edges - near) / (far - near)).mean()


def background_colour(
    sigma: Tensor, rgb: Tensor, m: Tensor, t: Tensor, is_bg: Tensor, last_delta: float
) -> Tensor:
    """Colour [B, R, 3] the background slot renders on its own: the composed field
    ``sigma`` [B, R, N], ``rgb`` [B, R, N, 3] at samples ``t`` [B, R, N] with each point's
    density scaled by the background's mask ``m`` [B, R, N, K] (``is_bg`` [B, K]). With
    ``ModelConfig.bg_outside_fg`` that mask is 1 outside the foreground region and 0 inside
    it, so this is the scene with the objects' region emptied."""
    m_bg = (m * is_bg[:, None, None, :].to(m.dtype)).sum(dim=-1)
    rgb_bg, _, _, _ = volume_render(sigma * m_bg, rgb, t, last_delta=last_delta)
    return rgb_bg


def object_mass(acc: Tensor, slot_probs: Tensor | None, gate: Tensor | None = None) -> Tensor:
    """Mean over rays of ``acc * (1 - P_bg)``: the rendered weight the object slots take
    (the last slot is the background). ``ModelConfig.fg_mass`` puts a price on it.

    Args:
        acc: [B, R] accumulated opacity; slot_probs: [B, R, K] per-pixel slot distribution.
        gate: [B, R] weight of each ray's price (``ModelConfig.fg_mass_halo``, see
            :func:`halo_gate`); None = every ray alike.
    Raises:
        ValueError: ``slot_probs`` is None (rendered with ``need_aux=False``).
    """
    if slot_probs is None:
        raise ValueError(
            "object_mass (ModelConfig.fg_mass) needs the slot distribution; render with "
            "need_aux=True"
        )
    mass = acc * (1.0 - slot_probs[..., -1])
    return mass.mean() if gate is None else (mass * gate).mean()


def soft_matter(
    sigma: Tensor, t: Tensor, far_r: Tensor, share: Tensor, length: float | None = None
) -> Tensor:
    """Mean over rays of ``sum_i share_i alpha_i (1 - alpha_i)``: how much half-transparent
    matter the rays meet (``ModelConfig.fg_binary`` puts a price on it). 0 for empty space
    and for solid matter alike.

    Args:
        sigma: [B, R, N] composed densities at the sorted samples ``t`` [B, R, N].
        far_r: [B, R] each ray's far bound (the last interval ends there, as in
            :func:`connectivity_loss`).
        share: [B, R, N] the object slots' share of each point (``1 - m_bg``).
        length: None = ``alpha_i`` is sample ``i``'s opacity over its own interval
            ``delta_i``. A length ``L`` = ``alpha_i = 1 - exp(-sigma_i L)`` and each term
            is weighted by ``delta_i / L``: the line integral of soft matter in units of
            ``L``, which does not depend on where the samples fall (fine samples crowd at
            surfaces, where short intervals make even dense matter look half-transparent).
    Returns:
        scalar float32 tensor.
    """
    if t.shape != sigma.shape or share.shape != sigma.shape or far_r.shape != sigma.shape[:-1]:
        raise ValueError(
            f"soft_matter: expected sigma, t, share [B, R, N] and far_r [B, R]; got sigma "
            f"{tuple(sigma.shape)}, t {tuple(t.shape)}, share {tuple(share.shape)}, far_r "
            f"{tuple(far_r.shape)}"
        )
    edges = _edges_to_far(t, far_r)
    delta = edges[..., 1:] - edges[..., :-1]
    sig = sigma.float().clamp(0.0, SIGMA_GUARD)
    if length is None:
        alpha = 1.0 - torch.exp(-sig * delta)
        return (share.float() * alpha * (1.0 - alpha)).sum(dim=-1).mean()
    alpha = 1.0 - torch.exp(-sig * length)
    return (share.float() * alpha * (1.0 - alpha) * (delta / length)).sum(dim=-1).mean()


def halo_gate(bg_rgb: Tensor | None, target: Tensor, tau: float) -> Tensor:
    """``exp(-|bg_rgb - target|^2 / tau^2)`` per ray [B, R], without gradient: 1 where the
    background alone renders the pixel's colour (``ModelConfig.fg_mass_halo``).

    Raises:
        ValueError: ``bg_rgb`` is None (the model rendered without it).
    """
    if bg_rgb is None:
        raise ValueError(
            "halo_gate (ModelConfig.fg_mass_halo) needs the background's own colour; render "
            "with need_aux=True"
        )
    with torch.no_grad():
        return torch.exp(-(bg_rgb.float() - target.float()).square().sum(dim=-1) / tau**2)
