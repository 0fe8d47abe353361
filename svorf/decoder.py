"""Slot decoder T(Z, E(I)) -> S (paper 3.2, appendix "Transformer-based module").

Where it sits: between the image encoder (``svorf.encoder``) and the object fields
(``svorf.field``): ``SVORF.encode`` = encoder + one of the modules here.

Both modules take the feature map [B, C, h, w] and return slots [B, K, D]; the last slot is
the background. Initial slots (both modules) = Linear(avg_pool(E(I))) + K learned positional
encodings (paper: "global image feature ... as initial object slots ... combining with K
learned positional encodings"); the learned per-slot encodings also break the symmetry
between slots and give the background slot its identity.

Choices where the paper is silent (documented, config fields where they are sizes):
- pre-norm layers (LayerNorm before each sub-layer, final LayerNorm): trains from scratch
  without warm-up tricks; the paper's warm-up is kept by the training code anyway.
- the flattened features get a LayerNorm and a fixed 2D sine positional encoding (DETR style)
  added to the keys only, so cross-attention can bind slots to image locations.
- Slot Attention (ablation) keeps the same deterministic initialisation instead of
  Gaussian sampling, since the background slot must stay the last one.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from .config import ModelConfig


def sine_pos_2d(h: int, w: int, dim: int, device=None, dtype=None) -> Tensor:
    """Fixed 2D sine positional encoding (DETR), [h*w, dim], row-major over (y, x).

    dim/4 frequencies each for sin(y), cos(y), sin(x), cos(x); zero padded to ``dim``.
    """
    nf = max(dim // 4, 1)
    freqs = 1.0 / (10000.0 ** (torch.arange(nf, device=device, dtype=torch.float32) / nf))
    # Positions in pixels of the feature map; frequencies 1 ... 1e-4 rad/pixel (Vaswani).
    ys = torch.arange(h, device=device, dtype=torch.float32)
    xs = torch.arange(w, device=device, dtype=torch.float32)
    py = ys[:, None] * freqs[None]  # [h, nf]
    px = xs[:, None] * freqs[None]  # [w, nf]
    py = torch.cat([py.sin(), py.cos()], -1)[:, None, :].expand(h, w, 2 * nf)
    px = torch.cat([px.sin(), px.cos()], -1)[None, :, :].expand(h, w, 2 * nf)
    pos = torch.cat([py, px], -1).reshape(h * w, 4 * nf)[:, :dim]
    if pos.shape[-1] < dim:
        pos = F.pad(pos, (0, dim - pos.shape[-1]))
    return pos.to(dtype or torch.float32)


class MultiHeadAttention(nn.Module):
    """Multi-head attention with separate query / key / value widths.

    Shapes: q [B, Lq, Dq], k [B, Lk, Dk], v [B, Lk, Dv] -> [B, Lq, dim].
    ``key_mask`` [B, Lk] bool, True = attend (optional).

    ``fold_keys=True`` (the decoder's cross-attention: 8 slots against 1,024 feature tokens
    at the cpu scale) computes the same attention without projecting the keys and values:
    the key projection is folded into the queries (``q_h . (W_k,h k_t + b_k,h) = (W_k,h^T
    q_h) . k_t + q_h . b_k,h``) and the value projection is applied after the weighted sum
    (the weights of a query sum to 1, so ``sum_t a_t (W_v,h v_t + b_v,h) = W_v,h sum_t a_t
    v_t + b_v,h``). Same parameters and, up to float rounding, the same outputs, logits and
    gradients as :meth:`forward_reference`; the projections cost O(Lq Dk) per head instead
    of O(Lk dim). A scene whose keys are all masked gets NaN in both forms.
    """

    def __init__(
        self, dim: int, heads: int, q_dim: int, k_dim: int, v_dim: int, fold_keys: bool = False
    ) -> None:
        super().__init__()
        self.heads = heads
        self.fold_keys = fold_keys
        self.q = nn.Linear(q_dim, dim)
        self.k = nn.Linear(k_dim, dim)
        self.v = nn.Linear(v_dim, dim)
        self.o = nn.Linear(dim, dim)
        for lin in (self.q, self.k, self.v, self.o):
            nn.init.xavier_uniform_(lin.weight)
            nn.init.zeros_(lin.bias)

    def forward(
        self,
        q: Tensor,
        k: Tensor,
        v: Tensor,
        key_mask: Tensor | None = None,
        need_weights: bool = False,
    ) -> Tensor | tuple[Tensor, Tensor]:
        """Attention output [B, Lq, dim]; with ``need_weights`` also the attention logits
        [B, H, Lq, Lk] (softmax over the last axis gives the weights used)."""
        if not self.fold_keys:
            return self.forward_reference(q, k, v, key_mask, need_weights)
        B, Lq, _ = q.shape
        H = self.heads
        qh = self.q(q).view(B, Lq, H, -1)  # [B, Lq, H, dh]
        dh = qh.shape[-1]
        qk = torch.einsum("bihd,hdc->bhic", qh, self.k.weight.view(H, dh, -1))  # [B,H,Lq,Dk]
        qb = torch.einsum("bihd,hd->bhi", qh, self.k.bias.view(H, dh))  # [B, H, Lq]
        logits = (qk.reshape(B, H * Lq, -1) @ k.transpose(1, 2)).view(B, H, Lq, -1)
        logits = (logits + qb[..., None]) / math.sqrt(dh)
        if key_mask is not None:
            logits = logits.masked_fill(~key_mask[:, None, None, :], float("-inf"))
        w = torch.softmax(logits, dim=-1)
        agg = (w.reshape(B, H * Lq, -1) @ v).view(B, H, Lq, -1)  # [B, H, Lq, Dv]
        out = torch.einsum("bhic,hdc->bihd", agg, self.v.weight.view(H, dh, -1))
        out = self.o((out + self.v.bias.view(H, dh)).reshape(B, Lq, -1))
        return (out, logits) if need_weights else out

    def forward_reference(
        self,
        q: Tensor,
        k: Tensor,
        v: Tensor,
        key_mask: Tensor | None = None,
        need_weights: bool = False,
    ) -> Tensor | tuple[Tensor, Tensor]:
        """The textbook form: project queries, keys and values per head, then attend."""
        B, Lq, _ = q.shape
        Lk = k.shape[1]
        H = self.heads
        qh = self.q(q).view(B, Lq, H, -1).transpose(1, 2)
        kh = self.k(k).view(B, Lk, H, -1).transpose(1, 2)
        vh = self.v(v).view(B, Lk, H, -1).transpose(1, 2)
        mask = None if key_mask is None else key_mask[:, None, None, :]
        if not need_weights:
            out = F.scaled_dot_product_attention(qh, kh, vh, attn_mask=mask)
            return self.o(out.transpose(1, 2).reshape(B, Lq, -1))
        logits = qh @ kh.transpose(-1, -2) / math.sqrt(qh.shape[-1])  # [B, H, Lq, Lk]
        if mask is not None:
            logits = logits.masked_fill(~mask, float("-inf"))
        w = torch.softmax(logits, dim=-1)
        out = self.o((w @ vh).transpose(1, 2).reshape(B, Lq, -1))
        return out, logits


class DecoderLayer(nn.Module):
    """Pre-norm transformer decoder layer: [self-attn], cross-attn to features, FFN.

    slots [B, K, D], memory [B, T, C], memory_pos [1 or B, T, C] -> slots [B, K, D].
    """

    def __init__(
        self,
        dim: int,
        heads: int,
        ffn: int,
        mem_dim: int,
        self_attention: bool,
        value_pos: bool = False,
    ) -> None:
        super().__init__()
        self.self_attention = self_attention
        self.value_pos = value_pos  # ModelConfig.dec_value_pos
        if self_attention:
            self.norm_sa = nn.LayerNorm(dim)
            self.sa = MultiHeadAttention(dim, heads, dim, dim, dim)
        self.norm_ca = nn.LayerNorm(dim)
        self.ca = MultiHeadAttention(dim, heads, dim, mem_dim, mem_dim, fold_keys=True)
        self.norm_ff = nn.LayerNorm(dim)
        self.ff = nn.Sequential(nn.Linear(dim, ffn), nn.ReLU(inplace=True), nn.Linear(ffn, dim))

    def forward(
        self, x: Tensor, memory: Tensor, memory_pos: Tensor, need_attn: bool = False
    ) -> Tensor | tuple[Tensor, Tensor]:
        """Updated slots [B, K, D]; with ``need_attn`` also the cross-attention logits
        [B, H, K, T]."""
        if self.self_attention:
            h = self.norm_sa(x)
            x = x + self.sa(h, h, h)
        keys = memory + memory_pos
        values = keys if self.value_pos else memory
        attn = None
        if need_attn:
            upd, attn = self.ca(self.norm_ca(x), keys, values, need_weights=True)
        else:
            upd = self.ca(self.norm_ca(x), keys, values)
        x = x + upd
        x = x + self.ff(self.norm_ff(x))
        return (x, attn) if need_attn else x


class _SlotInit(nn.Module):
    """Initial slots Z: Linear(avg_pool(features)) + K learned positional encodings."""

    def __init__(self, feat_dim: int, dim: int, num_slots: int) -> None:
        super().__init__()
        self.proj = nn.Linear(feat_dim, dim)
        self.pos = nn.Parameter(torch.randn(num_slots, dim))  # N(0, 1) as nn.Embedding

    def forward(self, features: Tensor) -> Tensor:
        pooled = features.mean(dim=(2, 3))  # [B, C]
        return self.proj(pooled)[:, None, :] + self.pos[None]  # [B, K, D]


def _flatten_features(features: Tensor, norm: nn.LayerNorm) -> tuple[Tensor, Tensor]:
    """[B, C, h, w] -> (normalised tokens [B, h*w, C], sine positions [1, h*w, C])."""
    _, C, h, w = features.shape
    tokens = norm(features.flatten(2).transpose(1, 2))
    pos = sine_pos_2d(h, w, C, device=features.device, dtype=tokens.dtype)[None]
    return tokens, pos


class SlotTransformerDecoder(nn.Module):
    """sVORF's transformer module: initial slots -> ``dec_layers`` decoder layers -> LayerNorm.

    forward(features [B, C, h, w]) -> slots [B, K, D]. With ``self_attention=False`` each
    slot is computed from its own initial value and the image only (ablation "w/o SA").
    """

    def __init__(self, cfg: ModelConfig) -> None:
        super().__init__()
        D = cfg.slot_dim
        self.init = _SlotInit(cfg.feat_dim, D, cfg.num_slots)
        self.mem_norm = nn.LayerNorm(cfg.feat_dim)
        self.layers = nn.ModuleList(
            DecoderLayer(
                D, cfg.dec_heads, cfg.dec_ffn, cfg.feat_dim, cfg.self_attention, cfg.dec_value_pos
            )
            for _ in range(cfg.dec_layers)
        )
        self.out_norm = nn.LayerNorm(D)
        self.centre_temperature = cfg.centre_temperature

    def forward(
        self, features: Tensor, return_attn: bool = False, attn_over: str = "tokens"
    ) -> Tensor | tuple[Tensor, Tensor]:
        """Slots [B, K, D]; with ``return_attn`` also the last layer's cross-attention over
        the feature map, [B, K, h, w], summing to 1 per slot: ``attn_over="tokens"`` the
        weights the layer uses (softmax over tokens, mean over heads); ``"slots"`` the same
        logits normalised over the slots (each token shared out among the slots, as in
        Slot Attention; mean over heads), then over the tokens."""
        memory, pos = _flatten_features(features, self.mem_norm)
        x = self.init(features)
        attn = None
        for i, layer in enumerate(self.layers):
            if return_attn and i == len(self.layers) - 1:
                x, attn = layer(x, memory, pos, need_attn=True)
            else:
                x = layer(x, memory, pos)
        slots = self.out_norm(x)
        if not return_attn:
            return slots
        if attn_over == "slots":  # ModelConfig.centre_temperature sharpens the sharing
            w = torch.softmax(attn.float() / self.centre_temperature, dim=2).mean(dim=1) + 1e-8
            w = w / w.sum(dim=-1, keepdim=True)
        else:
            w = torch.softmax(attn.float(), dim=-1).mean(dim=1)
        return slots, w.reshape(*slots.shape[:2], *features.shape[-2:])


class SlotAttention(nn.Module):
    """Slot Attention (Locatello et al. 2020) for the "w Slot-Attention" ablation.

    Softmax over slots, weighted mean over tokens, GRU update, residual MLP; ``iters``
    iterations (3). forward(features [B, C, h, w]) -> slots [B, K, D].
    """

    def __init__(self, cfg: ModelConfig) -> None:
        super().__init__()
        D, C = cfg.slot_dim, cfg.feat_dim
        self.iters = cfg.slot_attn_iters
        self.value_pos = cfg.dec_value_pos
        self.init = _SlotInit(C, D, cfg.num_slots)
        self.mem_norm = nn.LayerNorm(C)
        self.norm_slots = nn.LayerNorm(D)
        self.q = nn.Linear(D, D, bias=False)
        self.k = nn.Linear(C, D, bias=False)
        self.v = nn.Linear(C, D, bias=False)
        self.gru = nn.GRUCell(D, D)
        self.norm_mlp = nn.LayerNorm(D)
        self.mlp = nn.Sequential(
            nn.Linear(D, cfg.dec_ffn), nn.ReLU(inplace=True), nn.Linear(cfg.dec_ffn, D)
        )
        self.out_norm = nn.LayerNorm(D)
        self.scale = D**-0.5

    def forward(
        self, features: Tensor, return_attn: bool = False, attn_over: str = "slots"
    ) -> Tensor | tuple[Tensor, Tensor]:
        """Slots [B, K, D]; with ``return_attn`` also the last iteration's attention,
        normalised over the tokens, [B, K, h, w] (Slot Attention's attention is a softmax
        over the slots already: ``attn_over`` is accepted for a common signature)."""
        memory, pos = _flatten_features(features, self.mem_norm)
        k = self.k(memory + pos)  # [B, T, D]
        v = self.v(memory + pos if self.value_pos else memory)
        slots = self.init(features)
        B, K, D = slots.shape
        for _ in range(self.iters):
            prev = slots
            q = self.q(self.norm_slots(slots))
            attn = torch.softmax(torch.einsum("btd,bkd->btk", k, q) * self.scale, dim=-1)
            attn = attn + 1e-8
            attn = attn / attn.sum(dim=1, keepdim=True)  # weighted mean over tokens
            updates = torch.einsum("btk,btd->bkd", attn, v)
            slots = self.gru(updates.reshape(B * K, D), prev.reshape(B * K, D)).view(B, K, D)
            slots = slots + self.mlp(self.norm_mlp(slots))
        slots = self.out_norm(slots)
        if not return_attn:
            return slots
        return slots, attn.transpose(1, 2).reshape(B, K, *features.shape[-2:])


def build_slot_module(cfg: ModelConfig) -> nn.Module:
    """The slot module named by ``cfg.slot_module``."""
    if cfg.slot_module == "transformer":
        return SlotTransformerDecoder(cfg)
    return SlotAttention(cfg)
