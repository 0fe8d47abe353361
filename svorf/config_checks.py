"""Consistency checks of :class:`svorf.config.ModelConfig` (run by its ``__post_init__``).

Every check raises ``ValueError`` with one line naming the field, the value and the fix.
Kept apart from the dataclass so the field list (with each field's source and reason) stays
readable on its own.
"""

from __future__ import annotations

from typing import Any


def check(cfg: Any) -> None:
    """Raise ``ValueError`` if the fields of ``cfg`` (a ``ModelConfig``; not imported here,
    which imports this module) are out of range or contradict each other."""
    if cfg.bf16_autocast not in (True, False, "auto"):
        raise ValueError(
            f"ModelConfig.bf16_autocast must be true, false or 'auto', got {cfg.bf16_autocast!r}"
        )
    positive = (
        "image_size",
        "enc_width",
        "feat_dim",
        "num_slots",
        "slot_dim",
        "dec_heads",
        "dec_ffn",
        "mlp_width",
        "comp_dim",
        "comp_heads",
        "n_coarse",
    )
    for name in positive:
        if getattr(cfg, name) <= 0:
            raise ValueError(f"ModelConfig.{name} must be > 0, got {getattr(cfg, name)}")
    if cfg.image_size % 8:
        raise ValueError(f"ModelConfig.image_size must be a multiple of 8, got {cfg.image_size}")
    if len(cfg.enc_blocks) != 3 or min(cfg.enc_blocks) < 1:
        raise ValueError(
            f"ModelConfig.enc_blocks must be 3 positive block counts, got {cfg.enc_blocks}"
        )
    if cfg.num_slots < 1:
        raise ValueError(f"ModelConfig.num_slots must be >= 1, got {cfg.num_slots}")
    if cfg.slot_dim % cfg.dec_heads:
        raise ValueError(
            f"ModelConfig.slot_dim ({cfg.slot_dim}) must be divisible by dec_heads "
            f"({cfg.dec_heads})"
        )
    if cfg.comp_dim % cfg.comp_heads:
        raise ValueError(
            f"ModelConfig.comp_dim ({cfg.comp_dim}) must be divisible by comp_heads "
            f"({cfg.comp_heads})"
        )
    if cfg.mlp_depth < 2:
        raise ValueError(f"ModelConfig.mlp_depth must be >= 2, got {cfg.mlp_depth}")
    if not (cfg.mlp_skip == 0 or 2 <= cfg.mlp_skip <= cfg.mlp_depth - 1):
        raise ValueError(
            f"ModelConfig.mlp_skip must be 0 or in [2, mlp_depth-1={cfg.mlp_depth - 1}], "
            f"got {cfg.mlp_skip}"
        )
    if cfg.dec_layers < 0 or cfg.hyper_hidden < 0 or cfg.n_fine < 0:
        raise ValueError("ModelConfig.dec_layers, hyper_hidden and n_fine must be >= 0")
    if not 0.0 <= cfg.near < cfg.far:
        raise ValueError(f"ModelConfig needs 0 <= near < far, got near={cfg.near}, far={cfg.far}")
    if cfg.box_half <= 0 or (cfg.fg_box is not None and cfg.fg_box <= 0):
        raise ValueError("ModelConfig.box_half and fg_box must be > 0")
    if cfg.bg_achromatic and cfg.composition == "slot_mixer":
        raise ValueError(
            "ModelConfig.bg_achromatic needs per-slot colours; composition='slot_mixer' "
            "mixes the slots before the colour is computed (set bg_achromatic=False)"
        )
    if cfg.bg_chroma_fade is not None:
        p0, p1 = cfg.bg_chroma_fade
        if not 0.0 <= p0 <= p1 <= 1.0 or cfg.bg_achromatic:
            raise ValueError(
                f"ModelConfig.bg_chroma_fade must be (p0, p1) with 0 <= p0 <= p1 <= 1 "
                f"(fractions of the run) and bg_achromatic=False, got "
                f"bg_chroma_fade={cfg.bg_chroma_fade}, bg_achromatic={cfg.bg_achromatic}"
            )
        if cfg.composition == "slot_mixer":
            raise ValueError(
                "ModelConfig.bg_chroma_fade needs per-slot colours; composition="
                "'slot_mixer' mixes the slots before the colour is computed "
                "(set bg_chroma_fade=None)"
            )
    if cfg.box_z is not None:
        lo, hi = cfg.box_z
        if not (cfg.clip_to_box and -cfg.box_half <= lo < hi <= cfg.box_half):
            raise ValueError(
                f"ModelConfig.box_z must be (floor, ceiling) with -box_half <= floor < "
                f"ceiling <= box_half and needs clip_to_box=True, got box_z={cfg.box_z}, "
                f"box_half={cfg.box_half}, clip_to_box={cfg.clip_to_box}"
            )
    if cfg.clip_floor_z is not None and not cfg.clip_to_box:
        raise ValueError(
            f"ModelConfig.clip_floor_z={cfg.clip_floor_z} needs clip_to_box=True (without "
            "the box every ray already reaches far); set clip_to_box=True or clip_floor_z=None"
        )
    if cfg.clip_floor_front and cfg.clip_floor_z is None:
        raise ValueError(
            "ModelConfig.clip_floor_front=True needs clip_floor_z (the ground plane's "
            "height); set clip_floor_z or clip_floor_front=False"
        )
    if cfg.bg_outside_fg and cfg.fg_box is None and cfg.fg_zmin is None:
        raise ValueError("ModelConfig.bg_outside_fg needs fg_box or fg_zmin (the region)")
    if cfg.bg_floor_slab is not None:
        if not cfg.bg_floor_slab > 0:
            raise ValueError(
                f"ModelConfig.bg_floor_slab must be > 0 (world units) or None, "
                f"got {cfg.bg_floor_slab}"
            )
        if not (cfg.bg_outside_fg and cfg.fg_zmin is not None and cfg.fg_box is not None):
            raise ValueError(
                "ModelConfig.bg_floor_slab needs bg_outside_fg=True, fg_zmin and fg_box "
                "(the slab lies under the foreground region)"
            )
    if cfg.bg_pos_freqs_xyz is not None:
        if not 0 <= cfg.bg_pos_freqs_xyz < cfg.pos_freqs_xyz:
            raise ValueError(
                f"ModelConfig.bg_pos_freqs_xyz must be in [0, pos_freqs_xyz="
                f"{cfg.pos_freqs_xyz}) or None, got {cfg.bg_pos_freqs_xyz}"
            )
        if not cfg.hypernetwork:
            raise ValueError(
                "ModelConfig.bg_pos_freqs_xyz limits the background slot's generated "
                "weights: it needs hypernetwork=True"
            )
    if not (cfg.comp_temperature > 0):
        raise ValueError(f"ModelConfig.comp_temperature must be > 0, got {cfg.comp_temperature}")
    for name in ("fg_mass", "fg_binary", "ray_distortion"):
        ramped = getattr(cfg, name)
        if ramped is not None:
            lam, p0, p1 = ramped
            if not (lam >= 0 and 0.0 <= p0 <= p1 <= 1.0):
                raise ValueError(
                    f"ModelConfig.{name} must be (lambda, p0, p1) with lambda >= 0 and "
                    f"0 <= p0 <= p1 <= 1 (fractions of the run), got {ramped}"
                )
    length = cfg.fg_binary_length
    if length is not None and (cfg.fg_binary is None or not length > 0):
        raise ValueError(
            f"ModelConfig.fg_binary_length must be a length > 0 (world units) and needs "
            f"fg_binary=(lambda, p0, p1); got {length} with fg_binary {cfg.fg_binary}"
        )
    if cfg.fg_binary_all and cfg.fg_binary is None:
        raise ValueError(
            "ModelConfig.fg_binary_all widens fg_binary's price to every slot: it needs "
            "fg_binary=(lambda, p0, p1)"
        )
    halo = cfg.fg_mass_halo
    if halo is not None and (cfg.fg_mass is None or not cfg.bg_outside_fg or not halo > 0):
        raise ValueError(
            "ModelConfig.fg_mass_halo (tau > 0) weights fg_mass's price: it needs fg_mass "
            f"and bg_outside_fg=True, got fg_mass_halo={halo}, fg_mass={cfg.fg_mass}, "
            f"bg_outside_fg={cfg.bg_outside_fg}"
        )
    if cfg.slot_locality is not None:
        if not cfg.slot_locality > 0:
            raise ValueError(
                f"ModelConfig.slot_locality must be > 0 or None, got {cfg.slot_locality}"
            )
        if cfg.composition == "slot_mixer":
            raise ValueError(
                "ModelConfig.slot_locality needs per-slot fields; composition='slot_mixer' "
                "mixes them (use slot_guided or density_weighted)"
            )
    if cfg.slot_locality_narrow is not None:
        r_end, p0, p1 = cfg.slot_locality_narrow
        if cfg.slot_locality is None or not (r_end > 0 and 0.0 <= p0 <= p1 <= 1.0):
            raise ValueError(
                "ModelConfig.slot_locality_narrow must be (r_end, p0, p1) with r_end > 0 "
                "and 0 <= p0 <= p1 <= 1 (fractions of the run), with slot_locality set; "
                f"got slot_locality_narrow={cfg.slot_locality_narrow}, "
                f"slot_locality={cfg.slot_locality}"
            )
    if cfg.slot_locality_xy and cfg.slot_locality is None:
        raise ValueError(
            "ModelConfig.slot_locality_xy shapes slot_locality's envelope: set "
            "slot_locality (a radius) too"
        )
    if cfg.slot_relative and cfg.slot_locality is None:
        raise ValueError(
            "ModelConfig.slot_relative measures positions from slot_locality's centres: set "
            "slot_locality (a radius) too"
        )
    if cfg.slot_centre != "learned" and cfg.slot_locality is None:
        raise ValueError(
            f"ModelConfig.slot_centre={cfg.slot_centre!r} places slot_locality centres: set "
            "slot_locality (a radius) too"
        )
    if not cfg.centre_temperature > 0:
        raise ValueError(
            f"ModelConfig.centre_temperature must be > 0, got {cfg.centre_temperature}"
        )
    if not cfg.centre_focal > 0:
        raise ValueError(f"ModelConfig.centre_focal must be > 0, got {cfg.centre_focal}")
    if cfg.last_delta <= 0 or cfg.sigma_max <= 0:
        raise ValueError("ModelConfig.last_delta and sigma_max must be > 0")
    if cfg.slot_mask_train != 0 and not 0 < cfg.slot_mask_train <= cfg.num_slots - 2:
        raise ValueError(
            f"ModelConfig.slot_mask_train must leave the background and at least one "
            f"object slot: 0 <= slot_mask_train <= num_slots-2={cfg.num_slots - 2}, "
            f"got {cfg.slot_mask_train}"
        )
    if cfg.slot_topk < 0:
        raise ValueError(
            f"ModelConfig.slot_topk must be >= 0 (0 or >= num_slots = all slots), "
            f"got {cfg.slot_topk}"
        )
    if not 0.0 < cfg.slot_keep_mass <= 1.0:
        raise ValueError(
            f"ModelConfig.slot_keep_mass must be in (0, 1] (1 = off), got {cfg.slot_keep_mass}"
        )
    for name in ("eval_early_stop", "eval_fine_min_weight"):
        v = getattr(cfg, name)
        if v is not None and not 0.0 < v < 1.0:
            raise ValueError(f"ModelConfig.{name} must be in (0, 1) or None (off), got {v!r}")
    if cfg.eval_mask_rule not in (None, "composite", "peak", "peak_background"):
        raise ValueError(
            f"ModelConfig.eval_mask_rule must be None (the paper's weighted masks), "
            f"'composite' (the same), 'peak' or 'peak_background', got {cfg.eval_mask_rule!r}"
        )
    if cfg.enc_up_kernel not in (None, 1, 3):
        raise ValueError(
            f"ModelConfig.enc_up_kernel must be None (3x3, the paper), 1 or 3, "
            f"got {cfg.enc_up_kernel!r}"
        )
    if cfg.slot_attn_iters < 1:
        raise ValueError(f"ModelConfig.slot_attn_iters must be >= 1, got {cfg.slot_attn_iters}")
