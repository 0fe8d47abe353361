"""sVORF: image -> slots -> object radiance fields -> slot-guided composition -> pixels.

Where it sits: the model the training code (``svorf.train``), the evaluation adapter of
``benchmark`` and the editing helpers (``svorf.edit``) use. Data conventions it expects:

- images [B, 3, H, W], float, values in [0, 1]; resized to ``cfg.image_size`` if needed;
- rays in the world frame of the dataset (z-up, origin = scene centre): rays_o [B, R, 3],
  rays_d [B, R, 3] unit vectors. ``t``/``depth`` are distances along rays_d, i.e. the
  Euclidean distance from the camera centre for unit directions (NOT the planar camera z of
  the dataset's depth files: depth_z = depth * <d, camera forward axis>);
- ``slot_mask`` [B, K] bool: True = slot used, False = masked off (packed-11 training).

One forward pass (paper Fig. 1): E(I) (``encoder``) -> T(Z, E(I)) (``decoder``) -> slots S
[B, K, D] -> hypernetwork phi_k = H(s_k) (``field``) -> for every sample point: K densities
and colours, composed with the slot-guided masks m (``compose``) -> volume rendering with
hierarchical sampling (``march.RayMarcher`` over the primitives of ``render``, calling back
:meth:`SVORF._query` with a ``march.QueryContext``); the coarse pass uses the same network
as the fine pass (one set of fields; the paper's parameter count leaves no room for a
second hypernetwork).

Per-point cost (the speed knobs of ``ModelConfig``): the slot masks m are computed first (they need only
gamma(x) and the slots; the composer is folded into per-scene matrices, exactly), then the
object fields are evaluated only at the (point, slot) pairs that matter: unmasked slots,
foreground slots inside ``fg_box``, and with ``slot_topk`` / ``slot_keep_mass`` the slots
holding most of each point's m (``field.ObjectFields.eval_pairs``). ``bf16_autocast`` runs
the matmuls in bfloat16 with float32 transmittance. ``python -m benchmark.tools.speedbench``
measures every knob; their tolerances are tested in tests/test_speed_knobs.py.

At evaluation only (no gradient, deterministic samples), ``eval_early_stop`` stops marching
a ray once its transmittance is below a threshold and ``eval_fine_min_weight`` evaluates fine
samples only in coarse bins of non-negligible weight (both in ``svorf.march``;
tests/test_eval_knobs.py; their curve on trained weights: ``benchmark run tradeoff``). Both
off by default: the exact path.
"""

from __future__ import annotations

import contextlib
from dataclasses import dataclass
from typing import Any

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from .compose import SlotGuidedComposer, compose, compose_density_weighted
from .config import ModelConfig, bf16_autocast_on, ramp
from .decoder import build_slot_module
from .encoder import ImageEncoder
from .field import CondParams, FieldParams, build_fields, positional_encoding
from .frames import azimuth_frame, centre_anchors, token_ground_points
from .losses import (
    background_colour,
    connectivity_loss,
    halo_gate,
    object_mass,
    ray_distortion,
    soft_matter,
)
from .march import FieldQuery, QueryContext, RayMarcher, ray_slot_probs
from .pairs import PairCount, eval_kept, select_pairs, selects_by_m
from .render import clip_rays_to_box


@dataclass
class RenderOutput:
    """What :meth:`SVORF.render_rays` returns (all float32).

    rgb: [B, R, 3] fine-pass colour.
    depth: [B, R] expected termination distance sum_i w_i t_i along the unit ray direction
        (world units; Euclidean distance from the ray origin, not planar z).
    acc: [B, R] accumulated opacity sum_i w_i (~1: the last interval is "infinite").
    slot_probs: [B, R, K] per-pixel slot distribution (paper 4.3): the soft masks m rendered
        with the composite weights, sum_i w_i m_ik / acc; rows sum to 1, masked-off slots are
        exactly 0; argmax over K is the segmentation label. None when need_aux=False.
    connectivity: scalar connectivity (distortion) loss; 0 when disabled or need_aux=False.
    coarse_rgb: [B, R, 3] coarse-pass colour (NeRF practice: also supervised, so the shared
        network learns the coarse density that drives importance sampling); equals ``rgb``
        when n_fine = 0.
    bg_rgb: [B, R, 3] colour the background slot renders on its own
        (:func:`~svorf.losses.background_colour`); only with ``ModelConfig.fg_mass_halo``
        and need_aux=True, else None.
    soft_matter: scalar :func:`~svorf.losses.soft_matter` of the fine pass (the object
        slots' half-transparent matter); only with ``ModelConfig.fg_binary`` and
        need_aux=True, else None.
    ray_distortion: scalar :func:`~svorf.losses.ray_distortion` of the fine pass (the
        composed ray's spread); only with ``ModelConfig.ray_distortion`` and need_aux=True,
        else None.
    """

    rgb: Tensor
    depth: Tensor
    acc: Tensor
    slot_probs: Tensor | None
    connectivity: Tensor
    coarse_rgb: Tensor
    bg_rgb: Tensor | None = None
    soft_matter: Tensor | None = None
    ray_distortion: Tensor | None = None


class SVORF(nn.Module):
    """The sVORF model (Qi et al., NeurIPS 2023) and its ablation variants (see ModelConfig).

    Example:
        >>> from svorf.config import model_config
        >>> model = SVORF(model_config("smoke", num_slots=4))
        >>> imgs = torch.rand(2, 3, 32, 32)
        >>> o = torch.tensor([0.0, -12.0, 6.0]).expand(2, 16, 3)
        >>> d = F.normalize(-o + 0.1 * torch.randn(2, 16, 3), dim=-1)
        >>> out = model(imgs, o, d)
        >>> out.rgb.shape, out.slot_probs.shape
        (torch.Size([2, 16, 3]), torch.Size([2, 16, 4]))
    """

    def __init__(self, cfg: ModelConfig) -> None:
        super().__init__()
        if not isinstance(cfg, ModelConfig):
            raise TypeError(f"SVORF: cfg must be a ModelConfig, got {type(cfg).__name__}")
        self.cfg = cfg
        self.encoder = ImageEncoder(
            cfg.enc_width,
            cfg.enc_blocks,
            cfg.feat_dim,
            cfg.enc_norm,
            cfg.enc_up_kernel or 3,
            full_res=cfg.enc_full_res,
        )
        self.slot_module = build_slot_module(cfg)
        self.fields = build_fields(cfg)
        self.composer: SlotGuidedComposer | None = None
        if cfg.composition != "density_weighted":
            self.composer = SlotGuidedComposer(cfg, self.fields.in_x)
        self.slot_centre: nn.Linear | None = None  # ModelConfig.slot_locality
        if cfg.slot_locality is not None and cfg.slot_centre in ("learned", "anchored"):
            self.slot_centre = nn.Linear(cfg.slot_dim, 3)
        self.pair_count: PairCount | None = None  # see count_pairs
        if cfg.bg_chroma_fade is not None:  # the background's colour share (1 = full colour)
            self.register_buffer("bg_chroma", torch.ones(()))
        if cfg.slot_locality_narrow is not None:  # the slot-locality radius now
            self.register_buffer("locality_radius", torch.tensor(float(cfg.slot_locality)))
        if cfg.fg_mass is not None:  # the price on the object slots' rendered weight now
            self.register_buffer("fg_mass_weight", torch.zeros(()))
        if cfg.fg_binary is not None:  # the price on soft object matter now
            self.register_buffer("fg_binary_weight", torch.zeros(()))
        if cfg.ray_distortion is not None:  # the price on the composed ray's spread now
            self.register_buffer("ray_distortion_weight", torch.zeros(()))
        if cfg.photo_l1 is not None:  # the absolute error's share of the photometric terms
            self.register_buffer("photo_l1_weight", torch.zeros(()))

    # ------------------------------------------------------------------ encoding
    def encode(self, images: Tensor, return_attn: bool = False) -> Tensor | tuple[Tensor, Tensor]:
        """Input view -> slots.

        Args:
            images: [B, 3, H, W] in [0, 1]; resized (bilinear, antialiased) to image_size.
            return_attn: also return each slot's attention over the feature map,
                [B, K, h, w] (pass it to :meth:`render_rays` as ``slot_attn``; needed with
                ``slot_centre="attention"``).
        Returns:
            slots [B, K, D]; slot K-1 is the background. With ``return_attn``: (slots, attn).
        """
        if images.dim() != 4 or images.shape[1] != 3:
            raise ValueError(
                f"SVORF.encode: images must be [B, 3, H, W], got {tuple(images.shape)}"
            )
        s = self.cfg.image_size
        p = next(self.encoder.parameters())
        images = images.to(device=p.device, dtype=p.dtype)
        if tuple(images.shape[-2:]) != (s, s):
            images = F.interpolate(
                images, size=(s, s), mode="bilinear", align_corners=False, antialias=True
            )
        if self.cfg.enc_bf16:  # the CNN under bf16 autocast where it is on; float32 out
            with self._autocast(images.device):
                feats = self.encoder(images)
            feats = feats.float()
        else:
            feats = self.encoder(images)
        if not return_attn:
            return self.slot_module(feats)
        over = "slots" if self.cfg.slot_centre == "attention_slots" else "tokens"
        return self.slot_module(feats, return_attn=True, attn_over=over)

    def encode_for_render(self, images: Tensor) -> tuple[Tensor, dict[str, Tensor]]:
        """(slots [B, K, D], the extra keyword arguments :meth:`render_rays` needs for them):
        ``{"slot_attn": ...}`` with ``slot_centre="attention"``, else ``{}``."""
        if self.cfg.slot_centre.startswith("attention") and self.cfg.slot_locality is not None:
            slots, attn = self.encode(images, return_attn=True)
            return slots, {"slot_attn": attn}
        return self.encode(images), {}

    # ------------------------------------------------------------------ rendering
    def render_rays(
        self,
        slots: Tensor,
        rays_o: Tensor,
        rays_d: Tensor,
        *,
        slot_mask: Tensor | None = None,
        perturb: bool = False,
        need_aux: bool = True,
        object_transforms: Tensor | None = None,
        input_c2w: Tensor | None = None,
        slot_attn: Tensor | None = None,
    ) -> RenderOutput:
        """Render rays of B scenes from their slots.

        Args:
            slots: [B, K, D] (last slot = background).
            rays_o: [B, R, 3] ray origins, world frame.
            rays_d: [B, R, 3] unit ray directions, world frame.
            slot_mask: [B, K] bool, True = slot used. Masked slots get m = 0 (removed from
                the composition softmax) and are left out of the connectivity loss. When
                every scene keeps the same number of slots, the masked ones are not
                evaluated at all.
            perturb: stratified jitter of the coarse samples and random fine quantiles
                (training); False gives deterministic samples (evaluation).
            need_aux: compute slot_probs and the connectivity loss.
            object_transforms: [B, K, 4, 4] affine maps moving each object (identity = not
                moved); slot k's sample points (and directions) are mapped by the inverse
                before its field and its composition logit are evaluated (paper 4.4).
            input_c2w: [B, 4, 4] camera-to-world of each scene's input view (the image the
                slots came from). With ``coord_frame="input_azimuth"`` the networks see
                coordinates rotated about z by minus that camera's azimuth
                (:func:`azimuth_frame`); None = the input camera is at azimuth 0. Ignored
                with ``coord_frame="world"``.
            slot_attn: [B, K, h, w] attention of each slot over the input view's feature
                map (``encode(..., return_attn=True)``); required with
                ``slot_centre="attention"`` (with ``input_c2w``), ignored otherwise.
        Returns:
            :class:`RenderOutput`.
        """
        B, K, D = self._check_render_inputs(slots, rays_o, rays_d, slot_mask, object_transforms)
        rays_o = rays_o.to(device=slots.device, dtype=torch.float32)
        rays_d = rays_d.to(device=slots.device, dtype=torch.float32)
        if object_transforms is not None:
            object_transforms = object_transforms.to(slots.device, torch.float32).expand(B, K, 4, 4)
        frame = None
        if self.cfg.coord_frame == "input_azimuth" and input_c2w is not None:
            if input_c2w.shape[-2:] != (4, 4) or input_c2w.reshape(-1, 4, 4).shape[0] not in (1, B):
                raise ValueError(
                    f"SVORF.render_rays: input_c2w must be [B={B}, 4, 4], "
                    f"got {tuple(input_c2w.shape)}"
                )
            frame = azimuth_frame(input_c2w.reshape(-1, 4, 4).to(slots.device)).expand(B, 3, 3)
        centres = self._centres(slots, slot_attn, input_c2w, frame)
        is_bg = torch.zeros(B, K, dtype=torch.bool, device=slots.device)
        is_bg[:, -1] = True
        index = None
        if slot_mask is not None:
            slot_mask = slot_mask.to(device=slots.device, dtype=torch.bool)
            counts = slot_mask.sum(dim=1).tolist()
            if min(counts) == 0:
                raise ValueError("SVORF.render_rays: slot_mask leaves a scene with no slot")
            if min(counts) == K:
                slot_mask = None
            elif min(counts) == max(counts):
                # Same number of slots everywhere: evaluate only the used ones.
                order = torch.argsort((~slot_mask).to(torch.int8), dim=1, stable=True)
                index = order[:, : counts[0]]  # used slots, ascending
                slots = slots.gather(1, index[..., None].expand(-1, -1, D))
                if centres is not None:
                    centres = centres.gather(1, index[..., None].expand(-1, -1, 3))
                is_bg = index == K - 1
                if object_transforms is not None:
                    object_transforms = object_transforms.gather(
                        1, index[..., None, None].expand(-1, -1, 4, 4)
                    )
                slot_mask = None
        out = self._render(
            slots, rays_o, rays_d, slot_mask, is_bg, perturb, need_aux, object_transforms, frame,
            centres,
        )  # fmt: skip
        if index is not None and out.slot_probs is not None:
            full = out.slot_probs.new_zeros(B, rays_o.shape[1], K)
            out.slot_probs = full.scatter(
                2, index[:, None].expand(-1, rays_o.shape[1], -1), out.slot_probs
            )
        return out

    def _check_render_inputs(self, slots, rays_o, rays_d, slot_mask, transforms):
        if slots.dim() != 3 or slots.shape[-1] != self.cfg.slot_dim:
            raise ValueError(
                f"SVORF.render_rays: slots must be [B, K, D={self.cfg.slot_dim}], "
                f"got {tuple(slots.shape)}"
            )
        B, K, D = slots.shape
        for name, r in (("rays_o", rays_o), ("rays_d", rays_d)):
            if r.dim() != 3 or r.shape[0] != B or r.shape[-1] != 3:
                raise ValueError(
                    f"SVORF.render_rays: {name} must be [B={B}, R, 3], got {tuple(r.shape)}"
                )
        if rays_o.shape != rays_d.shape:
            raise ValueError(
                f"SVORF.render_rays: rays_o {tuple(rays_o.shape)} and rays_d "
                f"{tuple(rays_d.shape)} differ"
            )
        if slot_mask is not None and tuple(slot_mask.shape) != (B, K):
            raise ValueError(
                f"SVORF.render_rays: slot_mask must be [B={B}, K={K}], got {tuple(slot_mask.shape)}"
            )
        if transforms is not None:
            if transforms.dim() != 4 or transforms.shape[-2:] != (4, 4) or transforms.shape[1] != K:
                raise ValueError(
                    f"SVORF.render_rays: object_transforms must be [B, K={K}, 4, 4], "
                    f"got {tuple(transforms.shape)}"
                )
            if self.cfg.composition == "slot_mixer":
                raise ValueError(
                    "SVORF.render_rays: object_transforms needs per-object fields; "
                    "composition='slot_mixer' has one mixed field per point"
                )
        return B, K, D

    def _autocast(self, device: torch.device):
        """bf16 autocast where ``cfg.bf16_autocast`` asks for it ("auto": native bf16 only)."""
        if bf16_autocast_on(self.cfg.bf16_autocast, device):
            return torch.autocast(device_type=device.type, dtype=torch.bfloat16)
        return contextlib.nullcontext()

    def slot_params(self, slots: Tensor) -> FieldParams | CondParams:
        """Per-slot field parameters of ``slots`` [B, K, D] (the hypernetwork's output),
        under bf16 autocast where the config asks for it (the hypernetwork's output layer
        then keeps only its float32 weight for backward: see ``field._RecastLinear``)."""
        with self._autocast(slots.device):
            return self.fields.params(slots)

    def _render(
        self, slots, rays_o, rays_d, slot_mask, is_bg, perturb, need_aux, transforms, frame,
        centres=None,
    ):  # fmt: skip
        cfg = self.cfg
        B, R, _ = rays_o.shape
        if cfg.clip_to_box:
            box = (cfg.box_half, cfg.box_z, cfg.clip_floor_z, cfg.clip_floor_front)
            near_r, far_r = clip_rays_to_box(rays_o, rays_d, cfg.near, cfg.far, *box)
        else:
            near_r = rays_o.new_full((B, R), cfg.near)
            far_r = rays_o.new_full((B, R), cfg.far)
        params = self.slot_params(slots)
        inv = None if transforms is None else torch.linalg.inv(transforms)
        ctx = self.query_context(
            slots, params, rays_o, rays_d, slot_mask, is_bg, inv, frame, centres=centres
        )
        # Evaluation-only knobs (ModelConfig.eval_*): deterministic samples, no gradient.
        evaluating = not perturb and not torch.is_grad_enabled()
        marcher = RayMarcher.from_config(self._query, cfg, evaluating)
        p = marcher.render(ctx, near_r, far_r, perturb)
        rgb, depth, w, acc, t, q = p.rgb, p.depth, p.weights, p.acc, p.t, p.q

        slot_probs = None
        connectivity = rgb.new_zeros(())
        if need_aux:
            rule = cfg.eval_mask_rule if evaluating else None
            slot_probs = ray_slot_probs(w, q.m, acc, rule, is_bg)
            if cfg.connectivity:
                connectivity = connectivity_loss(q.sigma_k, t, far_r, cfg.near, cfg.far, slot_mask)
        bg_rgb = None
        if need_aux and cfg.fg_mass_halo is not None:
            bg_rgb = background_colour(q.sigma, q.rgb, q.m, t, is_bg, marcher.last_delta)
        soft = None
        if need_aux and cfg.fg_binary is not None:
            if cfg.fg_binary_all:  # every slot's matter, the background's too
                share = torch.ones_like(q.sigma)
            else:
                share = 1.0 - (q.m * is_bg[:, None, None, :].to(q.m.dtype)).sum(dim=-1)
            soft = soft_matter(q.sigma, t, far_r, share, cfg.fg_binary_length)
        spread = None
        if need_aux and cfg.ray_distortion is not None:
            spread = ray_distortion(q.sigma, t, far_r, cfg.near, cfg.far)
        return RenderOutput(
            rgb, depth, acc, slot_probs, connectivity, p.coarse_rgb, bg_rgb, soft, spread
        )  # fmt: skip

    def _query(self, ctx: QueryContext, t: Tensor) -> FieldQuery:
        """Composed field at samples t [B, R, N] of every ray of ``ctx`` (the field query
        the :class:`~svorf.march.RayMarcher` of :meth:`render_rays` calls)."""
        slots, params, rays_o, rays_d = ctx.slots, ctx.params, ctx.rays_o, ctx.rays_d
        slot_mask, is_bg, inv, frame, centres = (
            ctx.slot_mask, ctx.is_bg, ctx.inv, ctx.frame, ctx.centres
        )  # fmt: skip
        cfg = self.cfg
        B, R, N = t.shape
        K = slots.shape[1]
        P = R * N
        x = (rays_o[:, :, None] + t[..., None] * rays_d[:, :, None]).reshape(B, P, 3)
        dirs = F.normalize(rays_d, dim=-1)  # [B, R, 3]
        if inv is not None:  # slot k sees the scene through its inverse transform
            xk = torch.einsum("bkij,bpj->bkpi", inv[..., :3, :3], x) + inv[:, :, None, :3, 3]
            dk = F.normalize(torch.einsum("bkij,brj->bkri", inv[..., :3, :3], dirs), dim=-1)
        else:
            xk, dk = x[:, None], dirs[:, None]  # [B, 1, P, 3], [B, 1, R, 3]
        Kx = xk.shape[1]
        # The networks see the input view's azimuth frame; the priors below use the world's.
        xn, dn = xk, dk
        if frame is not None:
            xn = torch.einsum("bij,bkpj->bkpi", frame, xk)
            dn = torch.einsum("bij,bkrj->bkri", frame, dk)
        # gamma() in float32 outside autocast (sin of large arguments is poor in bf16).
        gx = positional_encoding(xn / cfg.box_half, cfg.pos_freqs_xyz, cfg.pos_include_input)
        gd = positional_encoding(dn, cfg.pos_freqs_dir, cfg.pos_include_input)
        gd = gd[:, :, :, None].expand(B, Kx, R, N, gd.shape[-1]).reshape(B, Kx, P, -1)

        valid = None if slot_mask is None else slot_mask[:, None, :]  # [B, 1, K]
        if cfg.fg_box is not None or cfg.fg_zmin is not None:
            inside = torch.ones(xk.shape[:-1], dtype=torch.bool, device=xk.device)
            if cfg.fg_box is not None:
                inside = (xk.abs() <= cfg.fg_box).all(dim=-1)  # [B, Kx, P]
            if cfg.fg_zmin is not None:  # the floor belongs to the background slot
                inside = inside & (xk[..., 2] >= cfg.fg_zmin)
            if cfg.bg_outside_fg:  # the background slot only outside the foreground region
                bg_ok = ~inside
                if cfg.bg_floor_slab is not None:  # ... and only in the floor slab above it
                    over = (xk[..., :2].abs() <= cfg.fg_box).all(dim=-1)  # [B, Kx, P]
                    bg_ok = bg_ok & ~(over & (xk[..., 2] < cfg.fg_zmin - cfg.bg_floor_slab))
                inside, bg_ok = inside.expand(B, K, P), bg_ok.expand(B, K, P)
                fg_ok = torch.where(is_bg[:, :, None], bg_ok, inside).transpose(1, 2)
            else:
                fg_ok = (inside.expand(B, K, P) | is_bg[:, :, None]).transpose(1, 2)  # [B, P, K]
            valid = fg_ok if valid is None else valid & fg_ok

        gx_f, gd_f = gx, gd  # what the slots' fields see
        if cfg.slot_relative and centres is not None:  # gamma(x - c_k); background: gamma(x)
            # The centres are placed by the locality envelope; the fields' loss does not move
            # them (detached: through gamma's K x P sines it made the step 1.29x dearer, 1.14x).
            rel = xn - centres.detach().masked_fill(is_bg[..., None], 0.0)[:, :, None, :]
            gx_f = positional_encoding(rel / cfg.box_half, cfg.pos_freqs_xyz, cfg.pos_include_input)
            gd_f = gd.expand(B, K, P, gd.shape[-1])

        log_g = None  # [B, K, P] log of the slot-locality envelopes (0 for the background)
        if centres is not None:
            diff = xn - centres[:, :, None, :]  # [B, K, P, 3]
            if cfg.slot_locality_xy:  # a vertical cylinder: distance in the floor plane
                diff = diff[..., :2]
            d2 = diff.square().sum(-1)  # [B, K, P]
            r = self.locality_radius if cfg.slot_locality_narrow is not None else cfg.slot_locality
            log_g = (-0.5 / r**2) * d2.masked_fill(is_bg[:, :, None], 0.0)

        with self._autocast(slots.device):
            if cfg.composition == "slot_mixer":
                a = self.composer(gx[:, 0], slots, valid)  # [B, P, K]
                sigma, rgb = self.fields.eval_mixed(params, a.to(gx.dtype), gx[:, 0], gd[:, 0])
                sigma, rgb, m = sigma.float(), rgb.float(), a
                # Connectivity for the mixed field: each slot's share of the density.
                sigma_k = a.transpose(1, 2) * sigma[:, None]
            elif cfg.composition == "slot_guided":
                # m needs only gamma(x) and the slots: it is known before any field runs, so
                # it can choose which (point, slot) pairs are worth evaluating.
                m = self.composer(gx if inv is not None else gx[:, 0], slots, valid, log_g)
                keep = select_pairs(cfg, m, valid)
                m_eval = m
                if keep is not None and selects_by_m(cfg, K):
                    # Renormalised over the evaluated slots: a partition of unity again.
                    m_eval = m * keep
                    m_eval = m_eval / m_eval.sum(dim=-1, keepdim=True).clamp_min(1e-30)
                sigma_k, rgb_k = self._eval_slots(params, gx_f, gd_f, keep)
                if log_g is not None:
                    sigma_k = sigma_k * log_g.exp()
                rgb_k = self._bg_colour(rgb_k, is_bg)
                sigma, rgb = compose(sigma_k, rgb_k, m_eval)
            else:
                keep = None if valid is None else valid.expand(B, P, K)
                sigma_k, rgb_k = self._eval_slots(params, gx_f, gd_f, keep)
                if log_g is not None:
                    sigma_k = sigma_k * log_g.exp()
                rgb_k = self._bg_colour(rgb_k, is_bg)
                sigma, rgb, m = compose_density_weighted(sigma_k, rgb_k, valid)
        return FieldQuery(
            sigma.view(B, R, N),
            rgb.view(B, R, N, 3),
            sigma_k.float().view(B, K, R, N),
            m.float().reshape(B, R, N, K),  # the composer's m is a [B, K, P] transpose
        )

    def _bg_colour(self, rgb_k: Tensor, is_bg: Tensor) -> Tensor:
        """``ModelConfig.bg_achromatic``: the background slot's colours [B, K, P, 3] made
        grey (the mean of the three channels); the other slots' unchanged. With
        ``bg_chroma_fade`` the background's colour is ``grey + c * (rgb - grey)`` with c the
        ``bg_chroma`` buffer (see :meth:`set_progress`)."""
        if self.cfg.bg_achromatic:
            grey = rgb_k.mean(dim=-1, keepdim=True).expand_as(rgb_k)
            return torch.where(is_bg[:, :, None, None], grey, rgb_k)
        if self.cfg.bg_chroma_fade is None:
            return rgb_k
        c = self.bg_chroma.to(rgb_k.dtype)
        grey = rgb_k.mean(dim=-1, keepdim=True)
        return torch.where(is_bg[:, :, None, None], grey + c * (rgb_k - grey), rgb_k)

    def set_progress(self, progress: float) -> None:
        """Tell the model how far its training run is (a fraction in [0, 1], as for the
        learning-rate schedule); sets what depends on it (``bg_chroma_fade``'s ``bg_chroma``
        buffer, ``slot_locality_narrow``'s ``locality_radius``, ``fg_mass``'s
        ``fg_mass_weight``, ``fg_binary``'s ``fg_binary_weight``, ``ray_distortion``'s
        ``ray_distortion_weight``, ``photo_l1``'s ``photo_l1_weight``). The training loop calls
        it before every step; a no-op without such fields. A new such field goes into
        ``svorf.config.PROGRESS_FIELDS`` too (a test checks), which the resume guard reads."""
        fade = self.cfg.bg_chroma_fade
        if fade is not None:
            self.bg_chroma.fill_(1.0 - ramp(progress, *fade))
        narrow = self.cfg.slot_locality_narrow
        if narrow is not None:
            r0, (r1, p0, p1) = float(self.cfg.slot_locality), narrow
            self.locality_radius.fill_(r0 + (r1 - r0) * ramp(progress, p0, p1))
        if self.cfg.fg_mass is not None:
            lam, p0, p1 = self.cfg.fg_mass
            self.fg_mass_weight.fill_(lam * ramp(progress, p0, p1))
        if self.cfg.fg_binary is not None:
            lam, p0, p1 = self.cfg.fg_binary
            self.fg_binary_weight.fill_(lam * ramp(progress, p0, p1))
        if self.cfg.ray_distortion is not None:
            lam, p0, p1 = self.cfg.ray_distortion
            self.ray_distortion_weight.fill_(lam * ramp(progress, p0, p1))
        if self.cfg.photo_l1 is not None:
            self.photo_l1_weight.fill_(ramp(progress, *self.cfg.photo_l1))

    def query_context(
        self,
        slots: Tensor,
        params: Any,
        rays_o: Tensor,
        rays_d: Tensor,
        slot_mask: Tensor | None,
        is_bg: Tensor,
        inv: Tensor | None = None,
        frame: Tensor | None = None,
        centres: Tensor | None = None,
    ) -> QueryContext:
        """What :meth:`_query` needs besides the samples (tests and speedbench build it too):
        slots [B, K, D], field params, rays [B, R, 3] (world), slot_mask [B, K] or None,
        is_bg [B, K], inverse object transforms [B, K, 4, 4] or None, frame [B, 3, 3] or
        None, slot-locality centres [B, K, 3] or None (None: the learned centres are
        derived here from the slots)."""
        if centres is None:
            centres = self._centres(slots)
        return QueryContext(slots, params, rays_o, rays_d, slot_mask, is_bg, inv, frame, centres)

    def _centres(
        self,
        slots: Tensor,
        slot_attn: Tensor | None = None,
        input_c2w: Tensor | None = None,
        frame: Tensor | None = None,
    ) -> Tensor | None:
        """Slot-locality centres [B, K, 3] (networks' frame), None when slot_locality is off.

        ``slot_centre="learned"``: e * tanh(Linear(s_k)). ``"anchored"``: a_k + e/2 *
        tanh(Linear(s_k)) (:func:`centre_anchors`; the background slot's centre is
        unused). ``"attention"``: the
        attention-weighted mean of the feature-map tokens' ground points (see
        :func:`token_ground_points`), rotated into the networks' frame by ``frame``.
        """
        cfg = self.cfg
        if cfg.slot_locality is None:
            return None
        extent = cfg.fg_box if cfg.fg_box is not None else cfg.box_half
        if cfg.slot_centre == "learned":
            assert self.slot_centre is not None
            return extent * torch.tanh(self.slot_centre(slots.float()))
        if cfg.slot_centre == "anchored":
            assert self.slot_centre is not None
            anchors = centre_anchors(slots.shape[1], extent, cfg.centre_height)
            offset = 0.5 * extent * torch.tanh(self.slot_centre(slots.float()))
            return anchors.to(slots.device) + offset
        B, K, _ = slots.shape
        if slot_attn is None or input_c2w is None:
            raise ValueError(
                f"SVORF.render_rays: slot_centre={cfg.slot_centre!r} needs slot_attn "
                "(encode(images, return_attn=True)) and input_c2w (the input camera)"
            )
        if slot_attn.dim() != 4 or tuple(slot_attn.shape[:2]) != (B, K):
            raise ValueError(
                f"SVORF.render_rays: slot_attn must be [B={B}, K={K}, h, w], "
                f"got {tuple(slot_attn.shape)}"
            )
        c2w = input_c2w.reshape(-1, 4, 4).to(slots.device, torch.float32).expand(B, 4, 4)
        h, w = slot_attn.shape[-2:]
        ground = token_ground_points(c2w, h, w, cfg.centre_focal, cfg.centre_height, extent)
        centres = torch.einsum("bkt,btc->bkc", slot_attn.float().reshape(B, K, h * w), ground)
        if frame is not None:
            centres = torch.einsum("bij,bkj->bki", frame, centres)
        return centres

    def _eval_slots(self, params, gx: Tensor, gd: Tensor, keep: Tensor | None):
        """Per-slot fields sigma_k [B, K, P], rgb_k [B, K, P, 3] (float32) at the kept pairs
        (:func:`svorf.pairs.eval_kept`; counted while :meth:`count_pairs` is on)."""
        return eval_kept(self.fields, params, gx, gd, keep, self.pair_count)

    def count_pairs(self) -> PairCount:
        """Count the (point, slot) pairs the fields evaluate from now on.

        Returns the live :class:`PairCount` (reset it with ``reset()``); counting costs one
        reduction per field call, so it is off until this is called. With
        ``slot_topk=2`` of 4 slots and nothing else dropped, ``fraction`` is 0.5.
        """
        if self.pair_count is None:
            self.pair_count = PairCount()
        return self.pair_count

    # ------------------------------------------------------------------ training API
    def forward(self, images: Tensor, rays_o: Tensor, rays_d: Tensor, **kw: Any) -> RenderOutput:
        """encode(images) + render_rays(slots, rays_o, rays_d, **kw).

        In training mode with ``cfg.slot_mask_train > 0`` and no ``slot_mask`` given, a
        random mask from :meth:`sample_slot_mask` is used (packed-11 setting).
        """
        slots, extra = self.encode_for_render(images)
        kw.update(extra)
        if self.training and self.cfg.slot_mask_train > 0 and kw.get("slot_mask") is None:
            kw["slot_mask"] = self.sample_slot_mask(slots.shape[0], device=slots.device)
        return self.render_rays(slots, rays_o, rays_d, **kw)

    def sample_slot_mask(
        self,
        batch: int,
        *,
        device: torch.device | str | None = None,
        generator: torch.Generator | None = None,
    ) -> Tensor | None:
        """[B, K] bool with ``cfg.slot_mask_train`` random object slots off per scene.

        The background slot (K-1) is never masked. None when slot_mask_train == 0.
        """
        n = self.cfg.slot_mask_train
        if n == 0:
            return None
        K = self.cfg.num_slots
        r = torch.rand(batch, K - 1, generator=generator, device=device)
        off = torch.argsort(r, dim=1)[:, :n]
        mask = torch.ones(batch, K, dtype=torch.bool, device=device)
        return mask.scatter(1, off, False)

    def loss(self, out: RenderOutput, target_rgb: Tensor) -> tuple[Tensor, dict[str, Tensor]]:
        """Training loss: MSE(fine) + coarse_loss_weight * MSE(coarse) + lambda * connectivity.

        The paper sums squared errors over the rays; the mean is used here (a constant
        factor absorbed by the learning rate, and independent of the batch size).

        Args:
            out: output of :meth:`render_rays` / :meth:`forward`.
            target_rgb: [B, R, 3] in [0, 1].
        Returns:
            total (scalar, differentiable) and detached scalars: "mse", "mse_coarse",
            "connectivity", "psnr", "total" (and "fg_mass" with ``ModelConfig.fg_mass``,
            "soft_matter" with ``ModelConfig.fg_binary``, "ray_distortion" with
            ``ModelConfig.ray_distortion``).
        """
        if target_rgb.shape != out.rgb.shape:
            raise ValueError(
                f"SVORF.loss: target_rgb must be {tuple(out.rgb.shape)}, got "
                f"{tuple(target_rgb.shape)}"
            )
        cfg = self.cfg
        target = target_rgb.to(out.rgb.device, torch.float32)
        mse = F.mse_loss(out.rgb, target)
        mse_c = F.mse_loss(out.coarse_rgb, target)
        total = self._photometric(out.rgb, target, mse)
        if cfg.n_fine > 0 and cfg.coarse_loss_weight > 0:
            total = total + cfg.coarse_loss_weight * self._photometric(
                out.coarse_rgb, target, mse_c
            )
        if cfg.connectivity:
            total = total + cfg.connect_lambda * out.connectivity
        fg_mass = None
        if cfg.fg_mass is not None:
            gate = None
            if cfg.fg_mass_halo is not None:
                gate = halo_gate(out.bg_rgb, target, cfg.fg_mass_halo)
            fg_mass = object_mass(out.acc, out.slot_probs, gate)
            total = total + self.fg_mass_weight * fg_mass
        if cfg.fg_binary is not None:
            if out.soft_matter is None:
                raise ValueError(
                    "SVORF.loss: ModelConfig.fg_binary needs the soft-matter term; render "
                    "with need_aux=True"
                )
            total = total + self.fg_binary_weight * out.soft_matter
        if cfg.ray_distortion is not None:
            if out.ray_distortion is None:
                raise ValueError(
                    "SVORF.loss: ModelConfig.ray_distortion needs the composed ray's "
                    "distortion; render with need_aux=True"
                )
            total = total + self.ray_distortion_weight * out.ray_distortion
        stats = {
            "mse": mse.detach(),
            "mse_coarse": mse_c.detach(),
            "connectivity": out.connectivity.detach(),
            "psnr": -10.0 * torch.log10(mse.detach().clamp_min(1e-10)),
            "total": total.detach(),
        }
        if fg_mass is not None:
            stats["fg_mass"] = fg_mass.detach()
        if cfg.fg_binary is not None:
            stats["soft_matter"] = out.soft_matter.detach()
        if cfg.ray_distortion is not None:
            stats["ray_distortion"] = out.ray_distortion.detach()
        return total, stats

    def _photometric(self, rgb: Tensor, target: Tensor, mse: Tensor) -> Tensor:
        """The photometric term: ``mse``, or with ``ModelConfig.photo_l1`` its blend with
        the absolute error scaled to ``mse``'s value (the scale carries no gradient)."""
        if self.cfg.photo_l1 is None:
            return mse
        b = self.photo_l1_weight
        l1 = F.l1_loss(rgb, target)
        scaled = l1 * (mse.detach() / l1.detach().clamp_min(1e-12))
        return (1.0 - b) * mse + b * scaled

    @torch.no_grad()
    def render_chunked(
        self, slots: Tensor, rays_o: Tensor, rays_d: Tensor, chunk: int = 4096, **kw: Any
    ) -> RenderOutput:
        """render_rays over chunks of ``chunk`` rays per scene, without gradients (evaluation).

        Args:
            slots [B, K, D], rays_o / rays_d [B, R, 3]; ``**kw`` as for render_rays.
        Returns:
            RenderOutput over all R rays (connectivity: ray-weighted mean over chunks).
        """
        if chunk <= 0:
            raise ValueError(f"SVORF.render_chunked: chunk must be > 0, got {chunk}")
        R = rays_o.shape[1]
        outs = [
            self.render_rays(slots, rays_o[:, i : i + chunk], rays_d[:, i : i + chunk], **kw)
            for i in range(0, R, chunk)
        ]
        sizes = [o.rgb.shape[1] for o in outs]
        probs = None
        if all(o.slot_probs is not None for o in outs):
            probs = torch.cat([o.slot_probs for o in outs], dim=1)
        conn = sum(o.connectivity * n for o, n in zip(outs, sizes)) / max(R, 1)
        return RenderOutput(
            torch.cat([o.rgb for o in outs], dim=1),
            torch.cat([o.depth for o in outs], dim=1),
            torch.cat([o.acc for o in outs], dim=1),
            probs,
            torch.as_tensor(conn, dtype=torch.float32, device=slots.device),
            torch.cat([o.coarse_rgb for o in outs], dim=1),
        )

    def count_parameters(self, trainable_only: bool = True) -> int:
        """Number of (trainable) parameters."""
        return sum(p.numel() for p in self.parameters() if p.requires_grad or not trainable_only)
