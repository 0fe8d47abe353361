"""Sampling and marching of one render pass of sVORF: samples along the rays, the field
queried at them, and their volume rendering.

Where it sits: between ``svorf.render`` (per-ray primitives that know nothing of slots:
``sample_stratified``, ``sample_pdf``, ``volume_render``, ``intervals``) and
``svorf.model``. ``SVORF.render_rays`` gathers what its field needs besides the samples
into a :class:`QueryContext` and asks a :class:`RayMarcher` for the pass; the marcher
calls back the model's field query ``query(ctx, t) -> FieldQuery`` and knows nothing of
the networks behind it.

One pass (NeRF hierarchical sampling): ``n_coarse`` stratified samples per ray, the
field there, volume rendering; then ``n_fine`` samples from the coarse weights, the field
there only (the coarse samples' values are reused: one shared network), and volume
rendering of the union. At evaluation only (no gradient, deterministic samples), two
knobs trade exactness for speed: ``early_stop`` (``ModelConfig.eval_early_stop``) stops
marching a ray once its transmittance is below the threshold, and ``fine_min_weight``
(``ModelConfig.eval_fine_min_weight``) evaluates fine samples only in coarse bins of
non-negligible weight. Both off: the exact path.

Shapes: B scenes, R rays per scene, N samples per ray, K slots.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor

from .config import ModelConfig
from .render import SIGMA_GUARD, intervals, sample_pdf, sample_stratified, volume_render

__all__ = [
    "MARCH_SEGMENTS",
    "FieldQuery",
    "MarchResult",
    "QueryContext",
    "QueryFn",
    "RayMarcher",
    "log_transmittance",
    "merge_queries",
    "ray_slot_probs",
]

#: Segments of one pass's samples between two transmittance checks of ``early_stop``: more
#: segments stop closer to the termination point but cost more (smaller) network calls.
MARCH_SEGMENTS = 4


@dataclass(frozen=True)
class QueryContext:
    """What a field query needs besides the samples (``SVORF.query_context`` builds it).

    slots: [B, K, D] (last slot = background).
    params: the per-slot field parameters of ``slots`` (``SVORF.slot_params``).
    rays_o, rays_d: [B, R, 3] ray origins and unit directions, world frame.
    slot_mask: [B, K] bool (True = slot used) or None (all used).
    is_bg: [B, K] bool, True for the background slot.
    inv: [B, K, 4, 4] inverse object transforms, or None (no object moved).
    frame: [B, 3, 3] rotation from the world to the networks' frame, or None (world).
    centres: [B, K, 3] slot-locality centres (networks' frame), or None (no locality).
    """

    slots: Tensor
    params: Any
    rays_o: Tensor
    rays_d: Tensor
    slot_mask: Tensor | None
    is_bg: Tensor
    inv: Tensor | None = None
    frame: Tensor | None = None
    centres: Tensor | None = None

    def with_rays(self, rays_o: Tensor, rays_d: Tensor) -> QueryContext:
        """The same scenes and slots with other rays ([B, R', 3] each)."""
        return dataclasses.replace(self, rays_o=rays_o, rays_d=rays_d)


@dataclass
class FieldQuery:
    """Field values at the samples of one pass.

    sigma: [B, R, N] composed density.
    rgb: [B, R, N, 3] composed colour.
    sigma_k: [B, K, R, N] per-slot densities.
    m: [B, R, N, K] soft slot masks.
    """

    sigma: Tensor
    rgb: Tensor
    sigma_k: Tensor
    m: Tensor


#: A field query: ``query(ctx, t [B, R, N]) -> FieldQuery`` at the points ``o + t d`` of
#: the context's rays (``SVORF._query``).
QueryFn = Callable[[QueryContext, Tensor], FieldQuery]


@dataclass
class MarchResult:
    """One rendered pass (all float32).

    rgb: [B, R, 3] colour of the final (fine, or coarse when n_fine = 0) samples.
    depth: [B, R] expected termination distance; acc: [B, R] accumulated opacity.
    weights: [B, R, N] volume-rendering weights of the final samples ``t`` [B, R, N],
        whose field values are ``q``.
    coarse_rgb: [B, R, 3] colour of the coarse samples alone.
    """

    rgb: Tensor
    depth: Tensor
    acc: Tensor
    weights: Tensor
    t: Tensor
    q: FieldQuery
    coarse_rgb: Tensor


def ray_slot_probs(
    w: Tensor, m: Tensor, acc: Tensor, rule: str | None = None, is_bg: Tensor | None = None
) -> Tensor:
    """Each ray's slot distribution [B, R, K] from its samples' weights w [B, R, N], soft
    masks m [B, R, N, K] and opacity acc [B, R] (``ModelConfig.eval_mask_rule``).

    None or ``"composite"`` (the paper): ``sum_i w_i m_i / acc``. ``"peak"``: ``m`` of the
    sample of largest weight. ``"peak_background"``: the peak sample's ``m`` where that
    sample belongs to a background slot (its arg-max slot is one of ``is_bg`` [B, K]), the
    composite elsewhere. Rays with acc ~ 0 fall back to the mean mask over the samples,
    so every row is a distribution in all forms.
    """
    eps = 1e-6
    mean_m = m.mean(dim=2)
    if rule != "peak":
        num = torch.einsum("brn,brnk->brk", w, m)
        comp = (num + eps * mean_m) / (acc[..., None] + eps)
        if rule != "peak_background":
            return comp
        if is_bg is None:
            raise ValueError("ray_slot_probs: the 'peak_background' rule needs is_bg [B, K]")
    peak = w.argmax(dim=2, keepdim=True)  # [B, R, 1]
    w_peak = w.gather(2, peak)
    m_peak = m.gather(2, peak[..., None].expand(-1, -1, -1, m.shape[-1]))[:, :, 0]
    probs = (w_peak * m_peak + eps * mean_m) / (w_peak + eps)
    if rule == "peak":
        return probs
    on_bg = is_bg.gather(1, m_peak.argmax(dim=-1))  # [B, R]: the peak sample is a background's
    return torch.where(on_bg[..., None], probs, comp)


def merge_queries(a: FieldQuery, b: FieldQuery, order: Tensor) -> FieldQuery:
    """Concatenate two queries along N and reorder the samples by ``order`` [B, R, N]."""
    B, R, N = order.shape
    K = a.m.shape[-1]

    def cat_gather(x: Tensor, y: Tensor, dim: int, idx: Tensor) -> Tensor:
        return torch.cat([x, y], dim=dim).gather(dim, idx)

    return FieldQuery(
        cat_gather(a.sigma, b.sigma, 2, order),
        cat_gather(a.rgb, b.rgb, 2, order[..., None].expand(B, R, N, 3)),
        cat_gather(a.sigma_k, b.sigma_k, 3, order[:, None].expand(B, K, R, N)),
        cat_gather(a.m, b.m, 2, order[..., None].expand(B, R, N, K)),
    )


def log_transmittance(
    t: Tensor, sigma: Tensor, prior: tuple[Tensor, Tensor] | None, last_delta: float
) -> Tensor:
    """log T in front of each sample t [B, R, N] (float32), from the densities sigma
    [B, R, N] and the samples ``prior`` = (t [B, R, M], sigma [B, R, M]) merged in along
    the ray, with the intervals of the merged, sorted samples as the volume renderer uses
    them (a sample's density affects only the samples after it)."""
    N = t.shape[-1]
    if prior is not None:
        t = torch.cat([prior[0], t], dim=-1)
        sigma = torch.cat([prior[1], sigma], dim=-1)
    t_s, order = torch.sort(t.float(), dim=-1, stable=True)
    tau = sigma.float().gather(-1, order).clamp(0.0, SIGMA_GUARD) * intervals(t_s, last_delta)
    log_t = -torch.cumsum(tau, dim=-1)
    log_t = torch.cat([torch.zeros_like(log_t[..., :1]), log_t[..., :-1]], dim=-1)
    return torch.empty_like(log_t).scatter(-1, order, log_t)[..., -N:]


class RayMarcher:
    """Samples, queries and renders the rays of one pass (see the module docstring).

    Args:
        query: the field query (``SVORF._query``).
        n_coarse, n_fine: samples per ray of the two passes (n_fine = 0: coarse only).
        last_delta: length of each ray's last interval (``ModelConfig.last_delta``).
        early_stop: transmittance below which a ray stops (evaluation only; None = off).
        fine_min_weight: coarse-bin weight below which fine samples are not evaluated
            (evaluation only; None = off).
    """

    def __init__(
        self,
        query: QueryFn,
        *,
        n_coarse: int,
        n_fine: int,
        last_delta: float,
        early_stop: float | None = None,
        fine_min_weight: float | None = None,
    ) -> None:
        self.query = query
        self.n_coarse = n_coarse
        self.n_fine = n_fine
        self.last_delta = last_delta
        self.early_stop = early_stop
        self.fine_min_weight = fine_min_weight

    @classmethod
    def from_config(cls, query: QueryFn, cfg: ModelConfig, evaluating: bool) -> RayMarcher:
        """The marcher of a model config; the ``eval_*`` knobs only when ``evaluating``
        (no gradient, deterministic samples)."""
        return cls(
            query,
            n_coarse=cfg.n_coarse,
            n_fine=cfg.n_fine,
            last_delta=cfg.last_delta,
            early_stop=cfg.eval_early_stop if evaluating else None,
            fine_min_weight=cfg.eval_fine_min_weight if evaluating else None,
        )

    def render(self, ctx: QueryContext, near: Tensor, far: Tensor, perturb: bool) -> MarchResult:
        """Render the rays of ``ctx`` between ``near`` and ``far`` ([B, R] each).

        ``perturb``: stratified jitter of the coarse samples and random fine quantiles
        (training); False gives deterministic samples.
        """
        R = near.shape[-1]
        stop, min_w = self.early_stop, self.fine_min_weight
        t_c = sample_stratified(near, far, R, self.n_coarse, perturb)
        if stop is None:
            q_c = self.query(ctx, t_c)
        else:
            q_c = self.coarse_marching(ctx, t_c, stop)
        rgb_c, depth, w, acc = volume_render(q_c.sigma, q_c.rgb, t_c, last_delta=self.last_delta)
        rgb, t, q = rgb_c, t_c, q_c
        if self.n_fine > 0:
            mids = 0.5 * (t_c[..., 1:] + t_c[..., :-1])
            bins = torch.cat([near[..., None], mids, far[..., None]], dim=-1)
            t_f = sample_pdf(bins, w, self.n_fine, det=not perturb)
            # The fine pass uses the union of coarse and fine samples (NeRF). The coarse
            # samples' field values are reused (same network), only t_f is evaluated.
            if stop is None and min_w is None:
                q_f = self.query(ctx, t_f)
            else:
                t_f, q_f = self.fine_pruned(ctx, bins, w, t_c, q_c, t_f, stop, min_w)
            t, order = torch.sort(torch.cat([t_c, t_f], dim=-1), dim=-1)
            q = merge_queries(q_c, q_f, order)
            rgb, depth, w, acc = volume_render(q.sigma, q.rgb, t, last_delta=self.last_delta)
        return MarchResult(rgb, depth, acc, w, t, q, rgb_c)

    def query_subset(self, ctx: QueryContext, t: Tensor, keep: Tensor) -> FieldQuery:
        """Composed field at the samples t [B, R, N] where keep [B, R, N] is True; elsewhere
        sigma, rgb, sigma_k and m are 0 (the caller fills what it needs).

        The kept samples of each scene are packed into pseudo-rays of one sample each (their
        ray's origin and direction), padded to the largest count over the B scenes, so only
        they (and the padding) reach the networks. Every per-point quantity of the field
        query depends on the point, its ray direction and its scene only, so kept values
        equal the dense ones up to float summation order.
        """
        B, R, N = t.shape
        K = ctx.slots.shape[1]
        if bool(keep.all()):
            return self.query(ctx, t)
        flat = keep.reshape(B, R * N)
        counts = flat.sum(dim=1)
        P = int(counts.max())
        sigma = t.new_zeros(B, R * N)
        rgb = t.new_zeros(B, R * N, 3)
        sigma_k = t.new_zeros(B, K, R * N)
        m = t.new_zeros(B, R * N, K)
        if P > 0:
            idx = torch.argsort((~flat).to(torch.int8), dim=1, stable=True)[:, :P]  # [B, P]
            ray = (idx // N)[..., None].expand(B, P, 3)
            sub = ctx.with_rays(ctx.rays_o.gather(1, ray), ctx.rays_d.gather(1, ray))
            qs = self.query(sub, t.reshape(B, R * N).gather(1, idx)[..., None])
            # Padding entries (scenes with fewer kept samples) add 0 to a kept sample.
            real = (torch.arange(P, device=t.device)[None] < counts[:, None]).float()
            sigma = sigma.scatter_add(1, idx, qs.sigma[..., 0] * real)
            ix3, ixk = idx[..., None].expand(B, P, 3), idx[..., None].expand(B, P, K)
            rgb = rgb.scatter_add(1, ix3, qs.rgb[:, :, 0] * real[..., None])
            sigma_k = sigma_k.scatter_add(
                2, idx[:, None].expand(B, K, P), qs.sigma_k[..., 0] * real[:, None]
            )
            m = m.scatter_add(1, ixk, qs.m[:, :, 0] * real[..., None])
        return FieldQuery(
            sigma.view(B, R, N), rgb.view(B, R, N, 3), sigma_k.view(B, K, R, N), m.view(B, R, N, K)
        )

    def query_marching(
        self,
        ctx: QueryContext,
        t: Tensor,
        stop: float | None,
        keep: Tensor | None = None,
        prior: tuple[Tensor, Tensor] | None = None,
        sigma_known: Tensor | None = None,
    ) -> tuple[FieldQuery, Tensor]:
        """Composed field at samples t [B, R, N] with early ray termination (evaluation).

        The N samples are taken in :data:`MARCH_SEGMENTS` segments along the ray; before
        each, the transmittance in front of every sample of the segment is computed from the
        densities known so far: ``prior`` = (t [B, R, M], sigma [B, R, M]) of samples
        already evaluated (the coarse pass, for the fine one) merged in, ``sigma_known``
        [B, R, N] of the samples where ``keep`` is False (not evaluated here), samples not
        yet evaluated counting as density 0 (an over-estimate of the transmittance: no
        sample is skipped too early). Samples whose transmittance is below ``stop``, and
        those where ``keep`` is False, are not evaluated.

        Returns:
            (query, evaluated [B, R, N] bool). Where not evaluated: sigma = sigma_known (or
            0), rgb = sigma_k = m = 0 (the caller fills m).
        """
        B, R, N = t.shape
        K = ctx.slots.shape[1]
        todo = torch.ones_like(t, dtype=torch.bool) if keep is None else keep
        sigma = t.new_zeros(B, R, N) if sigma_known is None else sigma_known.float().clone()
        rgb = t.new_zeros(B, R, N, 3)
        sigma_k = t.new_zeros(B, K, R, N)
        m = t.new_zeros(B, R, N, K)
        evaluated = torch.zeros_like(todo)
        log_stop = math.log(stop) if stop is not None else None
        seg = N if stop is None else max(1, -(-N // MARCH_SEGMENTS))
        for a in range(0, N, seg):
            b = min(N, a + seg)
            act = todo[..., a:b]
            if log_stop is not None and (a > 0 or prior is not None):
                log_t = log_transmittance(t, sigma, prior, self.last_delta)[..., a:b]
                act = act & (log_t >= log_stop)
            q = self.query_subset(ctx, t[..., a:b], act)
            sigma[..., a:b] = torch.where(act, q.sigma, sigma[..., a:b])
            rgb[..., a:b, :] = q.rgb
            sigma_k[..., a:b] = q.sigma_k
            m[..., a:b, :] = q.m
            evaluated[..., a:b] = act
        return FieldQuery(sigma, rgb, sigma_k, m), evaluated

    def coarse_marching(self, ctx: QueryContext, t_c: Tensor, stop: float) -> FieldQuery:
        """The coarse pass with ``early_stop``: :meth:`query_marching`, and each
        skipped sample (a suffix of its ray) takes the m of the ray's last evaluated sample,
        so slot_probs stay a distribution."""
        q, done = self.query_marching(ctx, t_c, stop)
        B, R, N = t_c.shape
        K = q.m.shape[-1]
        pos = torch.arange(N, device=t_c.device).expand(B, R, N)
        # The last evaluated index up to each sample (the first sample is always evaluated).
        src = torch.where(done, pos, 0).cummax(dim=-1).values
        m = torch.where(done[..., None], q.m, q.m.gather(2, src[..., None].expand(B, R, N, K)))
        return FieldQuery(q.sigma, q.rgb, q.sigma_k, m)

    def fine_pruned(
        self,
        ctx: QueryContext,
        bins: Tensor,
        w: Tensor,
        t_c: Tensor,
        q_c: FieldQuery,
        t_f: Tensor,
        stop: float | None,
        min_w: float | None,
    ) -> tuple[Tensor, FieldQuery]:
        """The fine pass with ``fine_min_weight`` / ``early_stop`` (evaluation).

        Args:
            bins: [B, R, Nc+1] coarse bin edges; w: [B, R, Nc] coarse weights; t_c, q_c:
                the coarse samples and their field; t_f: [B, R, Nf] fine samples.
        Returns:
            (t_f, q_f): fine samples dropped for a small bin weight are moved onto their
            bin's coarse sample and carry its values (a zero-length duplicate: the render is
            exactly that without them); samples past the termination point have density 0
            and the m of their bin's coarse sample (so slot_probs stay a distribution).
        """
        B, R, Nf = t_f.shape
        Nc = t_c.shape[-1]
        K = q_c.m.shape[-1]
        b_idx = torch.searchsorted(bins.contiguous(), t_f.contiguous(), right=True) - 1
        b_idx = b_idx.clamp(0, Nc - 1)  # the coarse bin (and sample) each fine sample is in
        keep = torch.ones_like(t_f, dtype=torch.bool)
        if min_w is not None:
            keep = w.gather(-1, b_idx) >= min_w
            t_f = torch.where(keep, t_f, t_c.gather(-1, b_idx))
        copy_sigma = q_c.sigma.gather(-1, b_idx)
        known = torch.where(keep, 0.0, copy_sigma)
        q, done = self.query_marching(ctx, t_f, stop, keep, (t_c, q_c.sigma), known)
        drop = ~keep
        rgb_c = q_c.rgb.gather(2, b_idx[..., None].expand(B, R, Nf, 3))
        sk_c = q_c.sigma_k.gather(3, b_idx[:, None].expand(B, q_c.sigma_k.shape[1], R, Nf))
        m_c = q_c.m.gather(2, b_idx[..., None].expand(B, R, Nf, K))
        return t_f, FieldQuery(
            q.sigma,  # the dropped samples' copies are in it already (sigma_known)
            torch.where(drop[..., None], rgb_c, q.rgb),
            torch.where(drop[:, None], sk_c, q.sigma_k),
            torch.where(done[..., None], q.m, m_c),
        )
