"""Composition of K object fields at a 3D point (paper 3.3 "Composing Mechanism").

Where it sits: ``SVORF.render_rays`` evaluates the K fields (``svorf.field``) at every sample
and calls this module to get the soft slot masks m [B, P, K] and the composed density and
colour; it does not know how the fields are parameterised.

- "slot_guided" (sVORF): D^c, a multi-head cross-attention with query Linear(gamma(x)) over
  keys/values Linear(s_k), gives z = q + Attn(q, S) (residual: keeps the point's identity);
  D^a scores z against linearly mapped slots, m = softmax_k(<A z, B s_k> / sqrt(d)) (the
  appendix: "computes the similarity between S and z after mapping them into the same space
  through a linear layer"); sigma = sum_k m_k sigma_k, c = sum_k m_k c_k.
- "density_weighted" (ablation, uORF style): m_k = sigma_k / sum_j sigma_j,
  sigma = sum_k sigma_k, c = sum_k m_k c_k.
- "slot_mixer" (appendix ablation): the same D^c + D^a weights a_k mix the slots into one
  field per point (see ``ObjectFields.eval_mixed``).

Masks: ``valid`` [B, P or 1, K] bool (True = slot may own the point) removes slots from the
softmax (masked-off slots, and foreground slots outside ``fg_box``); their m is exactly 0, and
a row with a single valid slot gives m = 1 for it, never NaN.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor, nn

from .config import ModelConfig

# Finite "minus infinity" for masked logits: exp(-1e4 - max) underflows to exactly 0 in
# float32 for any realistic logit, while a fully masked row stays finite (no NaN).
_MASK_LOGIT = -1e4


def masked_softmax(logits: Tensor, valid: Tensor | None, dim: int = -1) -> Tensor:
    """Softmax in float32 over ``dim`` with invalid entries exactly 0.

    A row with no valid entry returns all zeros (not NaN).
    """
    logits = logits.float()
    if valid is None:
        return torch.softmax(logits, dim=dim)
    p = torch.softmax(logits.masked_fill(~valid, _MASK_LOGIT), dim=dim)
    return p.masked_fill(~valid, 0.0)


class SlotGuidedComposer(nn.Module):
    """D^c (cross-attention, gamma(x) query over slots) and D^a (similarity -> softmax).

    Args:
        cfg: uses slot_dim, comp_dim, comp_heads.
        in_x: width of gamma(x).
    """

    def __init__(self, cfg: ModelConfig, in_x: int) -> None:
        super().__init__()
        dim, self.heads = cfg.comp_dim, cfg.comp_heads
        D = cfg.slot_dim
        self.q = nn.Linear(in_x, dim)
        self.k = nn.Linear(D, dim)
        self.v = nn.Linear(D, dim)
        self.o = nn.Linear(dim, dim)
        self.a_z = nn.Linear(dim, dim)  # D^a: maps z ...
        self.a_s = nn.Linear(D, dim)  # ... and the slots into the same space
        for lin in (self.q, self.k, self.v, self.o, self.a_z, self.a_s):
            nn.init.xavier_uniform_(lin.weight)
            nn.init.zeros_(lin.bias)

    def logits(self, gx: Tensor, slots: Tensor, valid: Tensor | None = None) -> Tensor:
        """D^a logits of every point against every slot.

        Args:
            gx: gamma(x) [B, P, Cx], or [B, K, P, Cx] for per-slot points (object
                transforms): then the logit of slot k is computed from slot k's own points.
            slots: [B, K, D].
            valid: [B, P or 1, K] bool or None (keys left out of D^c's attention).
        Returns:
            logits [B, P, K] (float of the compute dtype).
        """
        B, K, _ = slots.shape
        per_slot = gx.dim() == 4
        x = gx if per_slot else gx[:, None]  # [B, Kx, P, Cx]
        H = self.heads
        q = self.q(x)  # [B, Kx, P, dim]
        Kx, P, dim = q.shape[1], q.shape[2], q.shape[3]
        dh = dim // H
        k = self.k(slots).view(B, K, H, dh)
        v = self.v(slots).view(B, K, H, dh)
        att = torch.einsum("bxphd,bkhd->bxphk", q.view(B, Kx, P, H, dh), k) / math.sqrt(dh)
        vmask = None if valid is None else valid[:, None, :, None, :]  # [B, 1, P|1, 1, K]
        att = masked_softmax(att, vmask).to(q.dtype)
        z = q + self.o(torch.einsum("bxphk,bkhd->bxphd", att, v).reshape(B, Kx, P, dim))
        logits = torch.einsum("bxpc,bkc->bxpk", self.a_z(z), self.a_s(slots)) / math.sqrt(dim)
        if per_slot:  # slot k's logit from slot k's points: the diagonal over (Kx, K)
            return torch.diagonal(logits, dim1=1, dim2=3)  # [B, P, K]
        return logits[:, 0]

    def forward(self, gx: Tensor, slots: Tensor, valid: Tensor | None = None) -> Tensor:
        """Soft slot masks m [B, P, K] (float32, rows sum to 1 over valid slots)."""
        return masked_softmax(self.logits(gx, slots, valid), valid)


def compose(sigma_k: Tensor, rgb_k: Tensor, m: Tensor) -> tuple[Tensor, Tensor]:
    """sigma = sum_k m_k sigma_k, c = sum_k m_k c_k.

    Args:
        sigma_k: [B, K, P]; rgb_k: [B, K, P, 3]; m: [B, P, K].
    Returns:
        sigma [B, P], rgb [B, P, 3] (float32).
    """
    mt = m.float().transpose(1, 2)  # [B, K, P]
    sigma = (mt * sigma_k.float()).sum(dim=1)
    rgb = (mt[..., None] * rgb_k.float()).sum(dim=1)
    return sigma, rgb


def density_weights(sigma_k: Tensor, valid: Tensor | None = None, eps: float = 1e-8) -> Tensor:
    """uORF-style masks m_k = sigma_k / sum_j sigma_j over valid slots, [B, P, K].

    ``eps`` is added to every valid density, so where all densities vanish the valid slots
    share the point equally (no 0/0).

    Args:
        sigma_k: [B, K, P]; valid: [B, P or 1, K] bool or None.
    """
    s = sigma_k.float().transpose(1, 2) + eps  # [B, P, K]
    if valid is not None:
        s = s.masked_fill(~valid, 0.0)
    return s / s.sum(dim=-1, keepdim=True).clamp_min(1e-30)


def compose_density_weighted(
    sigma_k: Tensor, rgb_k: Tensor, valid: Tensor | None = None
) -> tuple[Tensor, Tensor, Tensor]:
    """uORF composition: sigma = sum_k sigma_k, c = sum_k (sigma_k / sum sigma) c_k.

    Returns:
        sigma [B, P], rgb [B, P, 3], m [B, P, K].
    """
    m = density_weights(sigma_k, valid)
    s = sigma_k.float()
    if valid is not None:
        s = s.masked_fill(~valid.transpose(1, 2), 0.0)
    _, rgb = compose(sigma_k, rgb_k, m)
    return s.sum(dim=1), rgb, m
