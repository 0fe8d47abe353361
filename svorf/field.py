"""Object radiance fields: positional encoding, hypernetwork, and the uORF-like ablation MLP.

Where it sits: ``SVORF.render_rays`` turns slots [B, K, D] into per-slot field parameters
once per call (:meth:`ObjectFields.params`), then evaluates every sample point of every ray
for all slots of all scenes at once (:meth:`ObjectFields.eval_fields`); ``svorf.compose``
combines the K outputs.

Object MLP (paper appendix A, "Object NeRF"): ``mlp_depth`` (4) layers of ``mlp_width`` (128)
channels. Layers 1..depth-1 take gamma(x) and are Linear+ReLU; the first layer's activation
is added to the activation of layer ``mlp_skip`` (3); the density is a linear head on the
last hidden activation (view-independent, as in NeRF); the last layer takes
[hidden, gamma(d)] and outputs RGB through a sigmoid. Density activation: softplus (or relu),
clamped to ``sigma_max``.

Glossary: B scenes, K slots, Kx = 1 (points shared by all slots) or K (per-slot points,
e.g. after an object transform), P points per scene (= R rays x N samples), D slot width,
W mlp width, Cx / Cd widths of gamma(x) / gamma(d), n selected (scene, slot, point) pairs,
T tiles of S rows.

Evaluation cost (measured at the ``cpu`` scale, 2 threads, fp32): the per-slot
MLPs are memory-bound, so what counts is how many [pairs x W] activations are written.

- Dense (:meth:`ObjectFields.eval_fields`): every slot at every point, one ``baddbmm`` per
  layer over B*K slot MLPs with the bias fused into the matmul and the ReLU applied in place
  on its output (no extra tensor). Measured alternatives that lost: bmm + separate bias add
  0.73-0.90x; carrying the biases in a constant-1 channel (width W+1) 0.86-1.02x;
  ``torch.compile`` of the MLP 0.53x after a 36 s compile (fp32) and 0.64x (bf16), so there
  is no compile switch.
- "Shared first layer": the first layer of all K slots is gamma(x) @ [W1_1 | ... | W1_K],
  one [P, Cx] x [Cx, K*W] matmul per scene instead of K*B copies of gamma(x). It is exact but
  measured 0.87x (fp32) / 0.43x (bf16): the [B, P, K, W] result has to be transposed to the
  per-slot layout of the next layers (a W-wide copy, wider than the Cx-wide gamma(x) copy it
  saves). Because the hypernetwork is linear in the (normalised) slot, gamma(x) @ W1_k =
  gamma(x) @ A0 + sum_d s_kd gamma(x) @ A_d can also be refactored through the hypernetwork
  matrix A [Cx*W, D]; that costs P*Cx*W*D multiply-adds instead of P*Cx*W*K, i.e. D/K (16x
  at cpu scale, 64x at paper scale) more, so the per-slot product above is the cheapest
  exact form. Neither is used.
- Sparse (:meth:`ObjectFields.eval_pairs`): only chosen (scene, slot, point) pairs (points
  inside ``fg_box``, unmasked slots, the top slots of each point). The pairs are grouped per
  (scene, slot), cut into tiles of S rows, and each tile runs with its slot's gathered
  weights: the cost is proportional to the number of pairs (plus < S padding rows per slot).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from .config import ModelConfig


def encoding_dim(n_freqs: int, include_input: bool = True, dims: int = 3) -> int:
    """Width of :func:`positional_encoding` for ``dims``-vectors."""
    return dims * (2 * n_freqs + int(include_input))


def positional_encoding(x: Tensor, n_freqs: int, include_input: bool = True) -> Tensor:
    """gamma(x) = [x, sin(2^l pi x), cos(2^l pi x)]_{l < n_freqs}.

    Args:
        x: [..., 3], expected roughly in [-1, 1] (positions are divided by ``box_half``).
    Returns:
        [..., encoding_dim(n_freqs, include_input)] in x's dtype.
    """
    parts = [x] if include_input else []
    if n_freqs > 0:
        freqs = math.pi * 2.0 ** torch.arange(n_freqs, device=x.device, dtype=x.dtype)
        xb = (x[..., None, :] * freqs[:, None]).flatten(-2)  # [..., L*3]
        parts += [torch.sin(xb), torch.cos(xb)]
    return torch.cat(parts, dim=-1)


def pe_frequency_mask(n_freqs: int, keep_freqs: int, include_input: bool = True) -> Tensor:
    """float32 [encoding_dim(n_freqs)]: 1 for the entries of :func:`positional_encoding`
    with frequency index < ``keep_freqs`` (and the raw input), 0 for the higher ones."""
    raw = torch.ones(3 * int(include_input))
    band = (torch.arange(n_freqs) < keep_freqs).float().repeat_interleave(3)  # [L*3]
    return torch.cat([raw, band, band])


@dataclass
class FieldParams:
    """Per-slot MLP parameters produced by the hypernetwork.

    hidden: [(weight [B, K, in, W], bias [B, K, W])] for the depth-1 hidden layers
        (in = Cx for the first, W after).
    head_w: [B, K, W, 4] (column 0 -> density, 1..3 -> rgb from the hidden activation).
    head_d: [B, K, Cd, 3] (rgb from gamma(d)).
    head_b: [B, K, 4].
    """

    hidden: list[tuple[Tensor, Tensor]]
    head_w: Tensor
    head_d: Tensor
    head_b: Tensor

    def select(self, index: slice) -> FieldParams:
        """Parameters of a subset of slots (``index`` on the K axis)."""
        return FieldParams(
            [(w[:, index], b[:, index]) for w, b in self.hidden],
            self.head_w[:, index],
            self.head_d[:, index],
            self.head_b[:, index],
        )

    @property
    def num_slots(self) -> int:
        return self.head_b.shape[1]


@dataclass
class CondParams:
    """Slot conditioning of the shared uORF-like MLP: slot_term [B, K, W]."""

    slot_term: Tensor

    def select(self, index: slice) -> CondParams:
        return CondParams(self.slot_term[:, index])

    @property
    def num_slots(self) -> int:
        return self.slot_term.shape[1]


class ObjectFields(nn.Module):
    """Common interface of :class:`HyperNetwork` and :class:`SlotConditionedMLP`."""

    def __init__(self, cfg: ModelConfig) -> None:
        super().__init__()
        self.width = cfg.mlp_width
        self.n_hidden = cfg.mlp_depth - 1
        self.skip = cfg.mlp_skip  # 1-based hidden layer index receiving the skip, 0 = none
        self.in_x = encoding_dim(cfg.pos_freqs_xyz, cfg.pos_include_input)
        self.in_d = encoding_dim(cfg.pos_freqs_dir, cfg.pos_include_input)
        self.density_act = cfg.density_act
        self.sigma_max = cfg.sigma_max

    def density(self, raw: Tensor) -> Tensor:
        """Raw density -> sigma in [0, sigma_max] (1/world unit)."""
        sigma = F.softplus(raw) if self.density_act == "softplus" else F.relu(raw)
        return sigma.clamp(max=self.sigma_max)

    def params(self, slots: Tensor):  # pragma: no cover - interface
        raise NotImplementedError

    def eval_fields(self, p, gx: Tensor, gd: Tensor) -> tuple[Tensor, Tensor]:
        """All slots' fields at all points.

        Args:
            p: output of :meth:`params` for slots [B, K, D].
            gx: gamma(x) [B, Kx, P, Cx]; gd: gamma(d) [B, Kx, P, Cd]; Kx in {1, K}.
        Returns:
            sigma [B, K, P] (>= 0), rgb [B, K, P, 3] in (0, 1).
        """
        raise NotImplementedError  # pragma: no cover

    def eval_mixed(self, p, a: Tensor, gx: Tensor, gd: Tensor) -> tuple[Tensor, Tensor]:
        """One field per point whose parameters are the a-weighted mix over slots (Slot Mixer).

        Args:
            a: mixing weights [B, P, K] (rows sum to 1); gx [B, P, Cx]; gd [B, P, Cd].
        Returns:
            sigma [B, P], rgb [B, P, 3].
        """
        raise NotImplementedError  # pragma: no cover

    def eval_reference(self, p, gx: Tensor, gd: Tensor) -> tuple[Tensor, Tensor]:
        """Slow per-scene, per-slot loop computing the same as :meth:`eval_fields` (tests)."""
        raise NotImplementedError  # pragma: no cover

    def eval_pairs(self, p, gx: Tensor, gd: Tensor, sel: Tensor) -> tuple[Tensor, Tensor]:
        """Fields only at the selected (scene, slot, point) pairs; exactly 0 at the others.

        Unselected pairs cost nothing (no matmul rows, no activations); the cost grows with
        ``sel.sum()``, not with B*K*P.

        Args:
            p: output of :meth:`params` for slots [B, K, D].
            gx: gamma(x) [B, Kx, P, Cx]; gd: gamma(d) [B, Kx, P, Cd]; Kx in {1, K}.
            sel: [B, K, P] bool, True = evaluate slot k at point p of scene b.
        Returns:
            sigma [B, K, P], rgb [B, K, P, 3], float32: what :meth:`eval_fields` gives where
            ``sel`` is True (same arithmetic, up to float summation order), 0 elsewhere.

        Example:
            >>> from svorf.config import model_config
            >>> f = HyperNetwork(model_config("smoke"))
            >>> p = f.params(torch.randn(2, 8, 32))
            >>> gx, gd = torch.randn(2, 1, 5, f.in_x), torch.randn(2, 1, 5, f.in_d)
            >>> sigma, rgb = f.eval_pairs(p, gx, gd, torch.rand(2, 8, 5) < 0.3)
            >>> sigma.shape, rgb.shape
            (torch.Size([2, 8, 5]), torch.Size([2, 8, 5, 3]))
        """
        B, K, P = sel.shape
        Kx = gx.shape[1]
        if gx.shape[0] != B or Kx not in (1, K) or gx.shape[2] != P:
            raise ValueError(
                f"eval_pairs: gx must be [B={B}, 1 or K={K}, P={P}, Cx], got {tuple(gx.shape)}"
            )
        flat = sel.reshape(-1).nonzero().squeeze(1)  # [n], sorted by (scene, slot, point)
        sigma = gx.new_zeros(B * K * P, dtype=torch.float32)
        rgb = gx.new_zeros(B * K * P, 3, dtype=torch.float32)
        if flat.numel() > 0:
            group = torch.div(flat, P, rounding_mode="floor")  # b * K + k
            # Row of the pair's point in gx flattened to [B * Kx * P, Cx].
            row = (
                flat
                if Kx == K
                else torch.div(group, K, rounding_mode="floor") * P + (flat - group * P)
            )
            counts = sel.reshape(B * K, P).sum(dim=1)
            gx, gd = _autocast_input(gx), _autocast_input(gd)  # gather half the bytes
            s, c = self._eval_rows(
                p, gx.reshape(-1, gx.shape[-1]), gd.reshape(-1, gd.shape[-1]), row, group, counts
            )
            sigma = sigma.index_copy(0, flat, s.float())
            rgb = rgb.index_copy(0, flat, c.float())
        return sigma.view(B, K, P), rgb.view(B, K, P, 3)

    def _eval_rows(
        self, p, gx: Tensor, gd: Tensor, row: Tensor, group: Tensor, counts: Tensor
    ) -> tuple[Tensor, Tensor]:
        """Fields of n pairs: point rows ``row`` [n] of gx [M, Cx] / gd [M, Cd], slot
        ``group`` [n] (= b * K + k, non-decreasing), ``counts`` [B * K] pairs per group.
        Returns sigma [n], rgb [n, 3]."""
        raise NotImplementedError  # pragma: no cover


class _RecastLinear(torch.autograd.Function):
    """``x @ W.T + b`` in a low-precision ``dtype``, as autocast computes it, but keeping
    the float32 ``W`` for the backward pass (cast again there) instead of its ``dtype``
    copy. Same values and gradients as ``nn.Linear`` under autocast."""

    @staticmethod
    def forward(ctx, x: Tensor, weight: Tensor, bias: Tensor, dtype: torch.dtype) -> Tensor:
        xc = x.to(dtype)
        ctx.save_for_backward(xc, weight)
        ctx.dtype, ctx.x_dtype = dtype, x.dtype
        with torch.autocast(x.device.type, enabled=False):
            return F.linear(xc, weight.to(dtype), bias.to(dtype))

    @staticmethod
    def backward(ctx, gy: Tensor):
        xc, weight = ctx.saved_tensors
        gx = gw = gb = None
        with torch.autocast(gy.device.type, enabled=False):
            gy = gy.to(ctx.dtype)
            g2 = gy.reshape(-1, gy.shape[-1])
            if ctx.needs_input_grad[0]:
                gx = (gy @ weight.to(ctx.dtype)).to(ctx.x_dtype)
            if ctx.needs_input_grad[1]:
                gw = (g2.t() @ xc.reshape(-1, xc.shape[-1])).to(weight.dtype)
            if ctx.needs_input_grad[2]:
                gb = g2.sum(0).to(weight.dtype)
        return gx, gw, gb, None


def _linear_autocast_recast(x: Tensor, lin: nn.Linear) -> Tensor:
    """``lin(x)``; under autocast through :class:`_RecastLinear`. For the hypernetwork's
    output layer: a [D, ~11k] weight applied to only B*K rows, whose bf16 copy (2.7 MB at
    the cpu config) autocast would keep alive until the backward pass reaches it."""
    dev = x.device.type
    if not torch.is_autocast_enabled(dev) or lin.bias is None:
        return lin(x)
    return _RecastLinear.apply(x, lin.weight, lin.bias, torch.get_autocast_dtype(dev))


def _autocast_input(x: Tensor) -> Tensor:
    """x in the autocast dtype when autocast is on for its device (what the next matmul would
    cast it to anyway), else x."""
    dev = x.device.type
    if x.is_floating_point() and torch.is_autocast_enabled(dev):
        return x.to(torch.get_autocast_dtype(dev))
    return x


def sparse_tile_rows(n: int, groups: int) -> int:
    """Tile height S for :meth:`HyperNetwork.eval_pairs`: a power of two near n / (4 groups),
    within [32, 256].

    Larger tiles mean fewer weight copies (one [in, W] matrix per tile) and bigger matmuls;
    smaller tiles less padding (below S rows per (scene, slot) group, ~S/2 on average) and
    activations that stay in cache. Measured at cpu scale (fp32 and bf16, 15-85% of the
    pairs kept): S = 128-256 fastest, 512-1024 up to 1.5x slower.
    """
    target = max(n / (4.0 * max(groups, 1)), 1.0)
    return 1 << max(5, min(8, round(math.log2(target))))


class HyperNetwork(ObjectFields):
    """H: slot s_i -> parameters phi_i of object MLP Phi_{phi_i} (paper eq. phi_i = H(s_i)).

    H = LayerNorm -> [Linear(D, hyper_hidden) -> ReLU] -> Linear(., n_params). Init: the
    output bias holds a He-initialised "base" MLP and the slot-dependent part has the same
    variance, so every generated MLP starts He-scaled (each part carries half the variance).
    """

    def __init__(self, cfg: ModelConfig) -> None:
        super().__init__(cfg)
        D, W = cfg.slot_dim, cfg.mlp_width
        self.norm = nn.LayerNorm(D)
        if cfg.hyper_hidden > 0:
            self.trunk: nn.Module = nn.Sequential(nn.Linear(D, cfg.hyper_hidden), nn.ReLU())
            h_in = cfg.hyper_hidden
        else:
            self.trunk = nn.Identity()
            h_in = D
        # (name, shape, fan_in, kind) of every generated tensor, in the output's order.
        layout: list[tuple[str, tuple[int, ...], int, str]] = []
        for i in range(self.n_hidden):
            fin = self.in_x if i == 0 else W
            layout += [(f"w{i}", (fin, W), fin, "relu_w"), (f"b{i}", (W,), fin, "bias")]
        layout += [
            ("head_w", (W, 4), W, "lin_w"),
            ("head_d", (self.in_d, 3), W + self.in_d, "lin_w"),
            ("head_b", (4,), W, "bias"),
        ]
        self.layout = layout
        self.n_params = sum(math.prod(s) for _, s, _, _ in layout)
        # ModelConfig.bg_pos_freqs_xyz: 1 for the gamma(x) inputs the background slot's
        # first layer may use, 0 for the higher frequencies (None: every input).
        self.bg_inputs: Tensor | None
        if cfg.bg_pos_freqs_xyz is None:
            self.bg_inputs = None
        else:
            self.register_buffer(
                "bg_inputs",
                pe_frequency_mask(cfg.pos_freqs_xyz, cfg.bg_pos_freqs_xyz, cfg.pos_include_input),
                persistent=False,
            )
        self.head = nn.Linear(h_in, self.n_params)
        self._init(h_in)

    @torch.no_grad()
    def _init(self, h_in: int) -> None:
        if isinstance(self.trunk, nn.Sequential):
            nn.init.kaiming_normal_(self.trunk[0].weight, nonlinearity="relu")
            nn.init.zeros_(self.trunk[0].bias)
        # Trunk output is LayerNorm'd (unit variance) or ReLU'd He (about unit 2nd moment).
        start = 0
        for _, shape, fan_in, kind in self.layout:
            n = math.prod(shape)
            sl = slice(start, start + n)
            start += n
            if kind == "bias":
                self.head.weight[sl].normal_(0.0, 0.02 / math.sqrt(h_in))
                self.head.bias[sl].zero_()
                continue
            gain = 2.0 if kind == "relu_w" else 1.0
            std = math.sqrt(gain / fan_in * 0.5)
            self.head.weight[sl].normal_(0.0, std / math.sqrt(h_in))
            self.head.bias[sl].normal_(0.0, std)

    def params(self, slots: Tensor) -> FieldParams:
        """slots [B, K, D] -> :class:`FieldParams` (one MLP per slot)."""
        B, K, _ = slots.shape
        flat = _linear_autocast_recast(self.trunk(self.norm(slots)), self.head)  # [B, K, n]
        out: dict[str, Tensor] = {}
        start = 0
        for name, shape, _, _ in self.layout:
            n = math.prod(shape)
            out[name] = flat[..., start : start + n].reshape(B, K, *shape)
            start += n
        if self.bg_inputs is not None:  # the background (last) slot: low frequencies only
            keep = torch.ones(K, self.in_x, 1, dtype=flat.dtype, device=flat.device)
            keep[-1, :, 0] = self.bg_inputs.to(flat.dtype)
            out["w0"] = out["w0"] * keep
        hidden = [(out[f"w{i}"], out[f"b{i}"]) for i in range(self.n_hidden)]
        return FieldParams(hidden, out["head_w"], out["head_d"], out["head_b"])

    def _mlp(self, x: Tensor, hidden: list[tuple[Tensor, Tensor]], head_w, head_b) -> Tensor:
        """G independent MLPs on [G, S, Cx] rows: hidden [(w [G, in, W], b [G, W])],
        head_w [G, W, 4], head_b [G, 4] -> [G, S, 4] (density logit, rgb logits before the
        gamma(d) term). Bias fused into ``baddbmm``; ReLU in place on the matmul's output
        (autograd keeps it: ReLU's backward needs only its result)."""
        h1 = h = x
        for i, (w, b) in enumerate(hidden):
            h = torch.baddbmm(b.unsqueeze(1), h, w).relu_()
            if i == 0:
                h1 = h
            elif i + 1 == self.skip:
                h = h + h1
        return torch.baddbmm(head_b.unsqueeze(1), h, head_w)

    def eval_fields(self, p: FieldParams, gx: Tensor, gd: Tensor) -> tuple[Tensor, Tensor]:
        B, K = p.head_b.shape[:2]
        Kx, P = gx.shape[1], gx.shape[2]
        BK = B * K
        # [B*K, P, C] layout: one baddbmm per layer for all slots of all scenes (a copy of
        # gamma(x) per slot; cast first under autocast, so the copy is half the bytes).
        x = _autocast_input(gx).expand(B, K, P, gx.shape[-1]).reshape(BK, P, -1)
        hidden = [(w.reshape(BK, *w.shape[2:]), b.reshape(BK, -1)) for w, b in p.hidden]
        out = self._mlp(x, hidden, p.head_w.reshape(BK, -1, 4), p.head_b.reshape(BK, 4))
        out = out.view(B, K, P, 4)
        if Kx == 1:  # gamma(d) shared by all slots: one bmm per scene
            d_term = torch.einsum("bpc,bkco->bkpo", gd[:, 0], p.head_d)
        else:
            d_term = torch.matmul(gd, p.head_d)  # [B, K, P, 3]
        sigma = self.density(out[..., 0])
        rgb = torch.sigmoid(out[..., 1:] + d_term)
        return sigma, rgb

    def _eval_rows(
        self, p: FieldParams, gx: Tensor, gd: Tensor, row: Tensor, group: Tensor, counts: Tensor
    ) -> tuple[Tensor, Tensor]:
        # Tiles: each (scene, slot) group's pairs fill ceil(count / S) tiles of S rows; a tile
        # runs with its group's weights (gathered per tile), so one baddbmm per layer covers
        # every pair of every slot. Padding rows read point 0 and are dropped at the end (no
        # gradient reaches them).
        G, n = counts.shape[0], row.shape[0]
        S = sparse_tile_rows(n, G)
        tiles = torch.div(counts + (S - 1), S, rounding_mode="floor")  # [G]
        T = int(tiles.sum())
        tile_start = torch.cumsum(tiles, 0) - tiles
        pair_start = torch.cumsum(counts, 0) - counts
        rank = torch.arange(n, device=row.device) - pair_start[group]
        dest = tile_start[group] * S + rank  # [n] row of each pair in the [T * S] tile layout
        tile_group = torch.repeat_interleave(
            torch.arange(G, device=row.device), tiles, output_size=T
        )
        src = row.new_zeros(T * S).index_copy_(0, dest, row)
        x = gx.index_select(0, src).view(T, S, -1)
        d = gd.index_select(0, src).view(T, S, -1)

        def per_tile(t: Tensor) -> Tensor:
            return t.reshape(G, *t.shape[2:]).index_select(0, tile_group)

        hidden = [(per_tile(w), per_tile(b)) for w, b in p.hidden]
        out = self._mlp(x, hidden, per_tile(p.head_w), per_tile(p.head_b))
        d_term = torch.bmm(d, per_tile(p.head_d))  # [T, S, 3]
        out = out.reshape(T * S, 4).index_select(0, dest)
        d_term = d_term.reshape(T * S, 3).index_select(0, dest)
        return self.density(out[:, 0]), torch.sigmoid(out[:, 1:] + d_term)

    def eval_mixed(
        self, p: FieldParams, a: Tensor, gx: Tensor, gd: Tensor
    ) -> tuple[Tensor, Tensor]:
        # sum_k a_k (h W_k + b_k) = [a_1 h, ..., a_K h] @ [W_1; ...; W_K] + a @ [b_1; ...; b_K]
        B, P, _ = a.shape

        def mixed_linear(h: Tensor, w: Tensor, b: Tensor | None) -> Tensor:
            xk = (a[..., None] * h[:, :, None, :]).reshape(B, P, -1)  # [B, P, K*in]
            wk = w.reshape(B, -1, w.shape[-1])  # [B, K*in, out]
            if b is None:
                return torch.bmm(xk, wk)
            return torch.baddbmm(torch.bmm(a, b), xk, wk)

        h1 = h = None
        for i, (w, b) in enumerate(p.hidden):
            h = F.relu(mixed_linear(gx if i == 0 else h, w, b))
            if i == 0:
                h1 = h
            elif i + 1 == self.skip:
                h = h + h1
        out = mixed_linear(h, p.head_w, p.head_b)
        sigma = self.density(out[..., 0])
        rgb = torch.sigmoid(out[..., 1:] + mixed_linear(gd, p.head_d, None))
        return sigma, rgb

    def eval_reference(self, p: FieldParams, gx: Tensor, gd: Tensor) -> tuple[Tensor, Tensor]:
        B, K = p.head_b.shape[:2]
        sig = torch.zeros(B, K, gx.shape[2], dtype=gx.dtype, device=gx.device)
        rgb = torch.zeros(B, K, gx.shape[2], 3, dtype=gx.dtype, device=gx.device)
        for b in range(B):
            for k in range(K):
                x = gx[b, min(k, gx.shape[1] - 1)]
                d = gd[b, min(k, gd.shape[1] - 1)]
                h1 = h = None
                for i, (w, bias) in enumerate(p.hidden):
                    h = torch.relu((x if i == 0 else h) @ w[b, k] + bias[b, k])
                    if i == 0:
                        h1 = h
                    elif i + 1 == self.skip:
                        h = h + h1
                out = h @ p.head_w[b, k] + p.head_b[b, k]
                sig[b, k] = self.density(out[:, 0])
                rgb[b, k] = torch.sigmoid(out[:, 1:] + d @ p.head_d[b, k])
        return sig, rgb


class SlotConditionedMLP(ObjectFields):
    """Ablation "w/o Hypernetwork": one shared MLP over [gamma(x), gamma(d), slot] (uORF-like).

    The slot enters the first layer (h1 = ReLU(A gamma(x) + S slot + b)); gamma(d) enters the
    RGB layer; everything else is the same MLP shape as the hypernetwork's fields. The slot
    term is computed once per slot, so all slots still run as one batched matmul.
    """

    def __init__(self, cfg: ModelConfig) -> None:
        super().__init__(cfg)
        W = cfg.mlp_width
        self.norm = nn.LayerNorm(cfg.slot_dim)
        self.lin_x = nn.Linear(self.in_x, W)
        self.lin_s = nn.Linear(cfg.slot_dim, W, bias=False)
        self.hidden = nn.ModuleList(nn.Linear(W, W) for _ in range(self.n_hidden - 1))
        self.head = nn.Linear(W, 4)
        self.head_d = nn.Linear(self.in_d, 3, bias=False)
        for lin in [self.lin_x, self.lin_s, *self.hidden]:
            nn.init.kaiming_normal_(lin.weight, nonlinearity="relu")
            if lin.bias is not None:
                nn.init.zeros_(lin.bias)
        with torch.no_grad():
            self.lin_x.weight.mul_(math.sqrt(0.5))  # x and slot terms share the variance
            self.lin_s.weight.mul_(math.sqrt(0.5))
        nn.init.zeros_(self.head.bias)

    def params(self, slots: Tensor) -> CondParams:
        return CondParams(self.lin_s(self.norm(slots)))

    def _trunk(self, h1: Tensor) -> Tensor:
        h = h1
        for i, lin in enumerate(self.hidden):
            h = F.relu(lin(h))
            if i + 2 == self.skip:
                h = h + h1
        return h

    def eval_fields(self, p: CondParams, gx: Tensor, gd: Tensor) -> tuple[Tensor, Tensor]:
        h1 = F.relu(self.lin_x(gx) + p.slot_term[:, :, None])  # [B, K, P, W]
        out = self.head(self._trunk(h1))
        sigma = self.density(out[..., 0])
        rgb = torch.sigmoid(out[..., 1:] + self.head_d(gd))
        return sigma, rgb

    def _eval_rows(
        self, p: CondParams, gx: Tensor, gd: Tensor, row: Tensor, group: Tensor, counts: Tensor
    ) -> tuple[Tensor, Tensor]:
        # One shared MLP: the pairs are just rows; only the slot term differs per pair.
        st = p.slot_term.reshape(-1, p.slot_term.shape[-1]).index_select(0, group)
        h1 = F.relu(self.lin_x(gx.index_select(0, row)) + st)
        out = self.head(self._trunk(h1))
        rgb = torch.sigmoid(out[:, 1:] + self.head_d(gd.index_select(0, row)))
        return self.density(out[:, 0]), rgb

    def eval_mixed(self, p: CondParams, a: Tensor, gx: Tensor, gd: Tensor) -> tuple[Tensor, Tensor]:
        # The slot enters linearly, so mixing slots == mixing their first-layer terms.
        h1 = F.relu(self.lin_x(gx) + torch.bmm(a, p.slot_term))
        out = self.head(self._trunk(h1))
        return self.density(out[..., 0]), torch.sigmoid(out[..., 1:] + self.head_d(gd))

    def eval_reference(self, p: CondParams, gx: Tensor, gd: Tensor) -> tuple[Tensor, Tensor]:
        B, K = p.slot_term.shape[:2]
        sig, rgb = [], []
        for b in range(B):
            for k in range(K):
                x = gx[b, min(k, gx.shape[1] - 1)]
                d = gd[b, min(k, gd.shape[1] - 1)]
                h1 = torch.relu(self.lin_x(x) + p.slot_term[b, k])
                out = self.head(self._trunk(h1))
                sig.append(self.density(out[:, 0]))
                rgb.append(torch.sigmoid(out[:, 1:] + self.head_d(d)))
        P = gx.shape[2]
        return torch.stack(sig).view(B, K, P), torch.stack(rgb).view(B, K, P, 3)


def build_fields(cfg: ModelConfig) -> ObjectFields:
    """:class:`HyperNetwork` if ``cfg.hypernetwork`` else :class:`SlotConditionedMLP`."""
    return HyperNetwork(cfg) if cfg.hypernetwork else SlotConditionedMLP(cfg)
