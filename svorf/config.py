"""Model configuration for sVORF: one frozen dataclass, saved as plain JSON.

Where it sits: ``svorf.model.SVORF(cfg)`` is built from a :class:`ModelConfig`; training,
evaluation and the benchmark obtain configs from :func:`model_config` (scales ``smoke``,
``cpu``, ``paper``, whose sizes live in the registry ``svorf.registry``) and store them
with ``cfg.to_dict()`` as JSON next to checkpoints.

Every number the paper (Qi et al., NeurIPS 2023, "sVORF") fixes is given with its source;
every choice the paper leaves open is a field here with a comment saying so.
"""

from __future__ import annotations

import dataclasses
import functools
import json
from dataclasses import dataclass
from typing import Any, Literal, get_args

from svorf.config_checks import check
from svorf.registry import SCALE_NAMES, SCALES

Composition = Literal["slot_guided", "density_weighted", "slot_mixer"]
SlotModule = Literal["transformer", "slot_attention"]
EncoderNorm = Literal["batch", "group", "none"]
DensityAct = Literal["softplus", "relu"]
Scale = Literal["smoke", "cpu", "paper"]
"""A scale name: the keys of ``svorf.registry.SCALES`` (tests/test_registry.py checks)."""
CoordFrame = Literal["world", "input_azimuth"]
SlotCentre = Literal["learned", "anchored", "attention", "attention_slots"]


@dataclass(frozen=True)
class ModelConfig:
    """All hyper-parameters of the sVORF model (architecture, sampling, loss, ablations).

    Units: ``near``, ``far``, ``box_half``, ``fg_box`` and ``last_delta`` are world units
    (the dataset's; CLEVR-567 cameras sit ~12.4 units from the scene centre).
    """

    # ---- image encoder (paper appendix A, "Image encoder") ----
    image_size: int = 256
    """Encoder input resolution (square); images are resized to it. Paper: 256."""
    enc_width: int = 64
    """Base channels of the ResNet34 trunk (conv2 width). Paper (ResNet34): 64."""
    enc_blocks: tuple[int, ...] = (3, 4, 6)
    """BasicBlocks per stage conv2, conv3, conv4. Paper (ResNet34): (3, 4, 6)."""
    enc_norm: EncoderNorm = "batch"
    """Normalisation in the trunk. ResNet34 uses BatchNorm ("batch"); "group" (8 groups)
    avoids train/eval statistics drift with the tiny batches of CPU training."""
    feat_dim: int = 512
    """Channels of the up-sampled feature map (appendix table "upsample layers"): 512."""
    enc_up_kernel: int | None = None
    """Kernel side of the three up-sampling convs: None = the paper's 3x3 (3 is stored as
    None), or 1. At 64x64 input the last 3x3 up-sampling conv is most of the encoder's
    work; 1x1 convs cut it about ninefold (a recipe lever for steps per minute, not the
    paper)."""
    enc_full_res: bool = False
    """Hand the slot decoder a feature map at the input resolution instead of half of it:
    a 3x3 stride-1 conv of the image (``enc_width`` channels) beside the last up-sampled
    map, merged by one 1x1 conv (4x the tokens). Not the paper (its map is at half the
    input). A recipe lever against the objects' blurred outline: where a token spans 2x2
    pixels, an edge is only known to the nearest token."""

    # ---- slot decoder (paper 3.2 and appendix "Transformer-based module") ----
    num_slots: int = 8
    """K, the last slot is the background. Paper: 8 on CLEVR-567, 5 on Room-*, 11 packed."""
    slot_dim: int = 512
    """D, slot width. Paper silent; 512 = the feature width, so that the avg-pooled feature
    initialises the slots without a bottleneck."""
    slot_module: SlotModule = "transformer"
    """"transformer" (sVORF) or "slot_attention" (ablation, appendix table)."""
    dec_layers: int = 3
    """Transformer decoder layers. Paper silent ("a standard transformer decoder"); 3 brings
    the total parameter count closest to the paper's 48.73M (see model_config)."""
    dec_heads: int = 8
    """Attention heads in the slot decoder. Paper silent; 8 as in DETR."""
    dec_ffn: int = 2048
    """FFN hidden width of the slot decoder. Paper silent; 4 x slot_dim as in DETR."""
    self_attention: bool = True
    """Self-attention among slots (ablation "w/o SA" sets False)."""
    dec_value_pos: bool = False
    """Add the image-token positional encoding to the cross-attention *values* too, not only
    to the keys (DETR's choice, the default). Paper silent. With positions in the values a
    slot carries where in the image the features it read lie, so quantities predicted from
    it (the ``slot_locality`` centres) can follow the objects; with keys only, the slot's
    position can come only from its learned initial encoding (a fixed layout). cpu recipe
    lever; the paper scale leaves it off."""
    slot_attn_iters: int = 3
    """Slot Attention iterations (Locatello et al. 2020), only for slot_module="slot_attention"."""

    # ---- object radiance fields (paper 3.3 and appendix "Object NeRF") ----
    hypernetwork: bool = True
    """True: a hypernetwork maps each slot to the weights of its own MLP (sVORF).
    False: ablation "w/o Hypernetwork": one shared uORF-like MLP conditioned on the slot."""
    hyper_hidden: int = 0
    """Hidden width of the hypernetwork; 0 = one linear map slot -> MLP parameters.
    Paper silent; linear keeps the count near 48.73M and makes Slot-Mixer mixing exact."""
    mlp_width: int = 128
    """Channels of each object MLP layer. Paper: 128."""
    mlp_depth: int = 4
    """Layers of each object MLP (the last outputs RGB). Paper: 4."""
    mlp_skip: int = 3
    """1-based index of the hidden layer whose activation gets the first layer's activation
    added (paper: "add the first layer's activation to the third layer's activation");
    0 disables the skip."""
    pos_freqs_xyz: int = 10
    """Frequencies L of gamma(x). Paper silent; NeRF's 10."""
    pos_freqs_dir: int = 4
    """Frequencies of gamma(d). Paper silent; NeRF's 4."""
    pos_include_input: bool = True
    """Whether gamma(.) also contains its raw input (as in NeRF's code)."""
    density_act: DensityAct = "softplus"
    """Density activation. Paper silent; softplus keeps gradients alive and, with the large
    last interval, bounds d(rgb)/d(raw density) (ReLU does not)."""
    sigma_max: float = 1e4
    """Upper clamp of every object density (1/world unit): bounded densities."""

    # ---- composition (paper 3.3 "Composing Mechanism", ablations) ----
    composition: Composition = "slot_guided"
    """"slot_guided" (sVORF, D^c + D^a), "density_weighted" (uORF-style mean, ablation) or
    "slot_mixer" (modified Slot-Mixer decoder, appendix ablation)."""
    comp_dim: int = 128
    """Width of D^c / D^a. Paper silent; 128 = mlp_width."""
    comp_heads: int = 4
    """Heads of the D^c cross-attention. Paper silent."""

    # ---- rendering (paper appendix A "Training details") ----
    n_coarse: int = 64
    """Stratified samples per ray. Paper: 64."""
    n_fine: int = 128
    """Importance samples per ray (hierarchical sampling); 0 = single pass. Paper: 128."""
    near: float = 6.0
    far: float = 20.0
    box_half: float = 4.5
    """Half side of the scene box [-box_half, box_half]^3 (world units). Positions are divided
    by it before gamma(x) so the scene maps to [-1, 1]^3; with clip_to_box it also bounds
    the samples. Every dataset keeps its content inside +-4.5."""
    clip_to_box: bool = False
    """Clip [near, far] of each ray to the scene box so samples lie only inside the scene
    (denser sampling for the same N). The paper samples [near, far]: off at paper scale."""
    box_z: tuple[float, float] | None = None
    """(floor, ceiling): with ``clip_to_box``, the samples of a ray lie in the box
    [-box_half, box_half]^2 x [floor, ceiling] instead of the cube (world units, world frame).
    A scene prior like ``fg_zmin``: on a ground plane at z = 0 with objects lower than the
    ceiling, the cube wastes about half of each ray's samples under the floor and more
    above the objects; the slab puts them where the objects are (about 3x denser on CLEVR's
    cameras), and the ray's last, opaque sample lies just under the floor, where the
    background slot paints it. None: the cube (paper)."""
    clip_floor_z: float | None = None
    """With ``clip_to_box``: the ground plane's height (world units, world frame). A downward
    ray that leaves the box before it reaches z = ``clip_floor_z`` (the floor seen beyond the
    box, half the floor pixels on CLEVR's cameras) gets samples out to that plane (at most
    ``far``) instead of ending on the box wall, where the background otherwise paints the
    far floor, so its depth is a bowl. Foreground density stays inside ``fg_box``. None:
    the box's exit (off at every scale)."""
    clip_floor_front: bool = False
    """With ``clip_floor_z``: a downward ray that reaches the ground plane before it enters
    the box (the floor in front of or beside the box, at the image's near corners) is
    sampled from ``near`` to that plane; otherwise its samples lie in the box under the
    floor and its depth is too far. Off at every scale."""
    coord_frame: CoordFrame = "input_azimuth"
    """Frame of the coordinates the networks see (gamma(x), gamma(d), the composition).
    "input_azimuth": the world frame rotated about the up axis (z) so that the input
    camera sits at azimuth 0 (uORF's convention for CLEVR/Room, whose code sVORF builds
    on: the object fields live in the input viewer's azimuth frame). A single image does
    not tell the camera's azimuth in a scene whose content is rotation-symmetric in
    distribution, so world coordinates cannot be predicted from it; without this the cpu
    scale learned only a rotation-averaged "mean scene" (docs/notes/cpu_recipe.md). The locality priors
    (``fg_box``, ``fg_zmin``, ``clip_to_box``) stay in the world frame. "world": the
    dataset's world frame. Renders pass the input camera as ``input_c2w``; without it the
    input camera is taken to be at azimuth 0. Configs saved before this field existed
    load as "world" (how they were trained)."""
    last_delta: float = 1e10
    """Length of the last sample's interval: "infinite" as in NeRF/uORF, so the last sample
    absorbs what the ray has left (the background slot supplies the colour)."""

    # ---- losses and training switches (paper 3.4, 4.6, 4.7) ----
    nvs: bool = True
    """Novel-view supervision; read by the training code to choose target views."""
    connectivity: bool = True
    """Connectivity regularisation (distortion loss per object field); "w/o CR" sets False."""
    connect_lambda: float = 0.01
    """lambda_connect. Paper: 0.01."""
    coarse_loss_weight: float = 1.0
    """Weight of the coarse-pass MSE (NeRF practice: coarse and fine colour both supervised,
    so the single network also learns a good coarse density for importance sampling)."""
    slot_mask_train: int = 0
    """Slots randomly masked off per scene per training step (packed-CLEVR-11 setting: 4 of 11).
    The background slot is never masked."""

    # ---- speed knobs (all off at paper scale, tolerances in tests/test_speed_knobs.py,
    # speeds from ``python -m benchmark.tools.speedbench``) ----
    bf16_autocast: bool | str = False
    """Run the hypernetwork, the per-point MLPs and the composition under bfloat16 autocast
    (faster matmuls and half-size activations on CPUs with AVX-512 BF16 / AMX). gamma(x), the
    slot softmax, the composed field, transmittance (log-space cumsums), importance sampling
    and the connectivity loss stay float32. Off = float32 everywhere (paper). ``"auto"``
    (what the ``cpu`` scale ships): only where the device has native bf16 (:func:`bf16_native`;
    where torch emulates it, e.g. AVX2 only, a cpu-scale step was measured 3-5x *slower*)."""
    enc_bf16: bool = False
    """Run the image encoder's CNN under the same autocast, only where ``bf16_autocast`` is
    on; the slot decoder gets a float32 map. At 64x64 the CNN is about half of a cpu-scale
    step (a recipe lever for steps per minute). Off = float32 CNN (paper)."""
    fg_box: float | None = None
    """If set, foreground (object) fields are evaluated only inside [-fg_box, fg_box]^3 and
    have density 0 outside, where they are also left out of the composition (the background
    slot owns that space). The out-of-box (point, slot) pairs are not computed at all.
    A modelling choice as much as a speed knob: None = everywhere (paper)."""
    slot_topk: int = 0
    """Evaluate the object fields at each point only for the ``slot_topk`` slots with the
    highest composition probability m (m comes from gamma(x) and the slots alone, before any
    field is evaluated). The composition then uses m renormalised over the evaluated slots;
    ``slot_probs`` still use the full m; slot k's density is 0 where it was not evaluated
    (also in the connectivity loss). Values >= the number of used slots evaluate all. Per
    point, |rgb - rgb_full| <= 1 - M and |sigma - sigma_full| <= (1 - M) max_k sigma_k,
    M = the evaluated slots' mass (ties in m are kept together). Applies to
    composition="slot_guided" only (the others need every slot's field first / mix fields):
    ignored otherwise. 0 = all slots (paper)."""
    slot_keep_mass: float = 1.0
    """Adaptive form of ``slot_topk``: at each point evaluate the highest-m slots until their
    mass M reaches ``slot_keep_mass`` (at least one slot), so the bound above holds with
    1 - M <= 1 - slot_keep_mass everywhere. Combined with slot_topk: both limits apply. The
    saving grows as m sharpens during training (at initialisation m is nearly uniform and
    nearly every slot is kept). slot_guided only, ignored otherwise. 1.0 = off (paper)."""

    # ---- evaluation-only speed knobs ("skip what a scene does not need"): read only
    # on the evaluation render path (no gradient, deterministic samples: ``render_chunked``,
    # ``predict_scene``), never in training; measured by ``benchmark run tradeoff``. Left out
    # of ``to_dict`` while off, so run keys and saved configs of earlier runs are unchanged ----
    eval_early_stop: float | None = None
    """Early ray termination at evaluation: the samples of each pass are marched in
    ``4`` segments along the ray, and a sample is evaluated only while the ray's
    transmittance in front of it (log space, float32, from the samples already evaluated,
    coarse and fine merged in the fine pass) is >= this threshold; later samples get
    density 0 (their composition masks m are copied from the ray's last evaluated sample,
    so slot_probs stay a distribution). The colour the skipped samples would add is at most
    the transmittance left, < threshold per channel, in the pass that skipped them (the
    fine pass's importance sampling sees the coarse result, so the final bound is close to,
    not exactly, the threshold: tests/test_eval_knobs.py states the tolerance). None = off:
    every sample evaluated, the exact path (paper)."""
    eval_fine_min_weight: float | None = None
    """Fine samples only where the coarse weights are non-negligible, at evaluation: a fine
    (importance) sample is evaluated only if the coarse weight w_i of the coarse bin it was
    drawn from is >= this value; the others are dropped from the union of samples (placed
    as zero-length duplicates of their bin's coarse sample, which renders exactly as
    without them). The coarse pass still covers the whole ray, so empty space keeps its
    coarse estimate and only the refinement there is skipped. Bins with w_i < 1/n_fine
    receive at most about one fine sample, so thresholds below that save little. None =
    off: every fine sample evaluated (paper)."""
    eval_mask_rule: str | None = None
    """How a pixel's slot distribution is read from its ray at evaluation. None
    (``"composite"``, the paper): the soft masks m of every sample weighted by its
    volume-rendering weight, ``sum_i w_i m_i / acc``. ``"peak"``: the soft masks of the
    sample of largest weight alone, the slot of the surface the ray meets; a thin,
    half-transparent rind of object matter in front of the floor then gives the pixel to
    the floor when the floor's sample outweighs each of the rind's. ``"peak_background"``:
    the peak sample decides only background against object (the pixel is the background
    slot's where the largest-weight sample belongs to it, as a floor sample below
    ``fg_zmin`` does), and which object from the weighted masks, as the paper reads it.
    Colour, depth and opacity are unchanged. Rays with no weight fall back to the mean
    mask in every form."""

    # ---- cpu-scale training recipe (docs/notes/cpu_recipe.md; all off at paper scale) ----
    fg_zmin: float | None = None
    """If set, foreground (object) slots have density 0 and composition weight 0 below the
    height z = fg_zmin (world units, z up; datasets put the floor at z = 0), so the floor
    belongs to the background slot: a label-free scene-layout prior in the spirit of uORF's
    locality box (combines with ``fg_box``). None = no such prior (paper)."""
    bg_outside_fg: bool = False
    """Background-slot prior: the background slot (the last) has density 0 and composition
    weight 0 inside the foreground region (inside ``fg_box`` and above ``fg_zmin``; one of
    them must be set), so it can only explain the floor and what lies outside, and the
    objects must be explained by foreground slots (with ``fg_zmin`` the two regions
    partition the scene). False = the background slot is a field like the others (paper)."""
    bg_floor_slab: float | None = None
    """Background floor prior (needs ``bg_outside_fg``, ``fg_zmin`` and ``fg_box``): over the
    foreground footprint (``|x|, |y| <= fg_box``) the background slot may hold density only
    in the slab ``fg_zmin - bg_floor_slab <= z < fg_zmin`` (world units), so it must paint
    the floor as a plane there instead of a bowl below it, and colour seen on an object in
    the input view cannot be pushed down under the floor by the background. Outside the
    footprint (walls, sky) it is unchanged. None = no such prior (paper and the cpu
    recipe; a lever, docs/notes/cpu_recipe.md)."""
    bg_achromatic: bool = False
    """The background slot's colour is achromatic: r = g = b = the mean of its three
    channels. A scene prior for grounds without hue (the CLEVR family's grey floor and
    sky): the background can still paint the floor's shading and the objects' shadows, but
    not a coloured object onto the floor behind it, so coloured objects must be explained by
    foreground slots. Wrong for coloured or textured backgrounds (the Room presets). False =
    no such prior (paper; a lever, docs/notes/cpu_recipe.md)."""
    bg_chroma_fade: tuple[float, float] | None = None
    """``bg_achromatic`` switched on gradually over training: the background slot keeps its
    full colour until the run's progress reaches ``p0``, is grey (as with
    ``bg_achromatic``) from ``p1`` on, and in between its colour is blended linearly
    towards grey (``grey + c * (rgb - grey)``, c from 1 down to 0). Progress is the run's
    fraction as for ``TrainConfig.lr_decay`` (steps, or training wall time of a
    time-budgeted run). The background first paints everything, objects included, and the
    foreground slots take the objects over from it; a grey background from step 0 stops
    that first stage (the foreground slots never start), so the prior comes after it. The
    current blend factor is a model buffer (``bg_chroma``), saved in checkpoints. None =
    off (paper; a lever, docs/notes/cpu_recipe.md)."""
    bg_pos_freqs_xyz: int | None = None
    """Background bandwidth (cpu recipe lever, hypernetwork only): the background slot's
    field sees only the first ``bg_pos_freqs_xyz`` frequencies of gamma(x) (the generated
    first-layer weights of the higher ones are zero for the last slot), so it can paint
    only smooth colour and density: detail the size of a small object must come from a
    foreground slot instead of being painted onto the floor. Measured on the cpu recipe
    (``python -m benchmark.tools.recipe diagnose``): most failures are small objects left to
    the background slot. A prior for plain CLEVR floors, not for textured rooms. None = the
    background sees every frequency (paper)."""
    comp_temperature: float = 1.0
    """Temperature T of the slot-guided composition: m = softmax_k(logits / T). T < 1
    sharpens the soft masks (more decomposition pressure from the first steps). 1.0 = paper."""
    fg_mass: tuple[float, float, float] | None = None
    """A price on what the object slots render, ``(lambda, p0, p1)``: the loss gains
    ``w * mean over rays of acc * (1 - P_bg)`` (the rendered weight the foreground slots
    take, from the per-pixel slot distribution), with ``w`` 0 until the run's progress
    reaches ``p0``, ``lambda`` from ``p1`` on, linear in between (progress as for
    ``bg_chroma_fade``). Matter an object slot holds where it changes no pixel's colour (a
    floor-coloured halo beside its object, which claims a rim of floor pixels in the
    masks) then costs something, while an object whose colour differs from the ground by
    more than about sqrt(lambda) per channel is still cheaper to keep. The current weight is
    a model buffer (``fg_mass_weight``), saved in checkpoints. None = off (paper; a lever,
    docs/notes/cpu_recipe.md)."""
    fg_mass_halo: float | None = None
    """With ``fg_mass``: the price only where the background alone explains the pixel. Each
    ray's ``acc * (1 - P_bg)`` is weighted by ``exp(-|C_bg - C|^2 / tau^2)`` (``tau`` = this
    value, RGB in [0, 1]; no gradient through the weight), with ``C`` the pixel's colour and
    ``C_bg`` the colour the background slot renders on its own along the ray (the composed
    field with the foreground region's density removed). A floor-coloured halo beside an
    object pays in full (the floor behind it has the pixel's colour); an object pixel, whose
    colour the floor behind does not have, pays almost nothing. Needs ``bg_outside_fg`` (the
    regions then partition the scene, so outside the foreground region the composed field
    is the background's). None = ``fg_mass`` prices every ray alike (paper). A lever, not
    in any recipe: a fine-tune probe narrowed the rim but cost FG-ARI at both seeds
    (docs/notes/cpu_recipe.md)."""

    fg_binary: tuple[float, float, float] | None = None
    """A price on soft object matter, ``(lambda, p0, p1)``: the loss gains ``w * mean over
    rays of sum_i f_i alpha_i (1 - alpha_i)``, with ``alpha_i = 1 - exp(-sigma_i delta_i)``
    the composed field's opacity of sample ``i`` (fine pass, intervals to the ray's far
    bound), ``f_i`` the object slots' share of that point (``1 - m_bg``), and ``w`` ramped
    as for ``fg_mass`` (0 before ``p0``, ``lambda`` from ``p1`` on). Empty space and solid
    matter cost nothing. A halo of thin object density beside an object, which a grazing
    ray gathers into the rim of floor the masks give to object slots, is half-transparent
    everywhere; unlike ``fg_mass`` an object pays nothing for being there. The weight is a
    model buffer (``fg_binary_weight``), saved in checkpoints. None = off (paper). A lever,
    not in any recipe: at the cpu scale, ramped from 0.4 of the run, it gave the rim back
    but lost small objects to the background; ramped from 0.8 it kept the objects and
    lifted ARI at one seed, at some FG-ARI (docs/notes/cpu_recipe.md)."""
    fg_binary_all: bool = False
    """With ``fg_binary``: every slot's half-transparent matter is priced, the background's
    too (``f_i = 1``), so that an object painted onto the floor is not free. False = the
    object slots' share only. A lever, not in any recipe: at the cpu scale it kept more
    small objects than the object-only price but still lost FG-ARI, and it thinned the
    floor beyond the sample box (docs/notes/cpu_recipe.md)."""
    fg_binary_length: float | None = None
    """With ``fg_binary``: each sample's opacity is taken over this fixed length (world
    units) instead of its own interval, and its term weighted by interval / length: the
    line integral of soft matter, whatever the sampling (per interval, the fine samples'
    short intervals at a surface make dense matter look half-transparent). None = per
    interval. Not measured yet."""

    ray_distortion: tuple[float, float, float] | None = None
    """Mip-NeRF 360's distortion loss on the *composed* ray, ``(lambda, p0, p1)``: the loss
    gains ``w * mean over rays of L(t, w_ray)`` (:func:`svorf.losses.ray_distortion`), with
    ``w_ray`` the fine pass's weights of the composed density (intervals to the ray's far
    bound, distances normalised by ``far - near`` as for ``connectivity``) and ``w`` ramped
    as for ``fg_mass`` (0 before ``p0``, ``lambda`` from ``p1`` on). The paper's
    connectivity term prices each object field's own spread; a ray that crosses an object's
    thin halo and then the floor splits its weight between two surfaces, which only this
    term prices. The weight is a model buffer (``ray_distortion_weight``). None = off
    (paper). A lever."""

    photo_l1: tuple[float, float] | None = None
    """The photometric terms (fine and coarse) move from squared to absolute error between
    progress ``p0`` and ``p1`` (``(p0, p1)``, ramped as ``fg_mass``): ``(1 - b) MSE + b s
    L1`` with ``s = MSE / L1`` detached, so the term keeps MSE's value and takes L1's
    gradient. In doubt about an object's edge, MSE renders the mean (a blurred edge, which
    the masks turn into a rim of floor claimed by the object), L1 the median. The weight
    ``b`` is a model buffer (``photo_l1_weight``). None = MSE (paper). A lever."""

    slot_locality_narrow: tuple[float, float, float] | None = None
    """``slot_locality``'s radius narrowed over training, ``(r_end, p0, p1)``: the radius is
    ``slot_locality`` until the run's progress reaches ``p0``, ``r_end`` from ``p1`` on,
    and linear in between (progress as for ``bg_chroma_fade``). A wide envelope lets the
    slots find the objects early; a narrow one late keeps a slot one or two units away
    from taking half of a large object (a split). The current radius is a model buffer
    (``locality_radius``), saved in checkpoints. None = a fixed radius (a lever,
    docs/notes/cpu_recipe.md)."""
    slot_locality: float | None = None
    """Slot-centred locality (cpu recipe): if set (a radius r, world units), every foreground
    slot also predicts a centre c_k = e * tanh(Linear(s_k)) (e = ``fg_box`` or ``box_half``;
    in the networks' frame, see ``coord_frame``), its density is multiplied by
    g_k(x) = exp(-|x - c_k|^2 / (2 r^2)) and log g_k is added to its composition logit.
    A slot can then only produce matter within a few r of its centre, so one slot cannot
    explain objects that lie far apart: decomposition pressure from the first step (the
    object-centric analogue of uORF's locality box). Label-free: the centres are learned
    from the reconstruction loss alone. None = off (paper)."""
    slot_locality_xy: bool = False
    """``slot_locality``'s envelope measured in the floor plane only: g_k(x) = exp(-|x_xy -
    c_k,xy|^2 / (2 r^2)), a vertical cylinder instead of a ball (z is up in every
    ``coord_frame``). Objects stand side by side on the floor, never on one another, so
    height says nothing about which slot a point belongs to, and a tall object's base is no
    nearer a neighbour's centre than its top is. In the cpu recipe: it lifted FG-ARI at
    both seeds by leaving fewer objects to the background, not by splitting large objects
    less (docs/notes/cpu_recipe.md). False = a ball (paper)."""
    slot_relative: bool = False
    """Object slots' fields see positions relative to their ``slot_locality`` centre c_k:
    gamma(x - c_k) instead of gamma(x) (the background slot and the composition keep
    gamma(x); c_k enters detached, placed by the locality envelope). A slot's field then
    describes its object around the origin, whatever its place in the scene, as
    object-centric fields with per-object frames do (uOCF, Luo et al. 2024); with gamma(x)
    it must place the object's edges through the positional encoding's global
    frequencies. Needs ``slot_locality`` (so not with ``composition="slot_mixer"``).
    False = gamma(x) (paper). A lever (docs/notes/cpu_recipe.md)."""
    slot_centre: SlotCentre = "learned"
    """Where the ``slot_locality`` centres come from. "learned": c_k = e * tanh(Linear(s_k)).
    "attention": geometry instead of a learned map: each token of the feature map is cast
    as a ray from the input camera (``input_c2w``, focal ``centre_focal``) to the plane
    z = ``centre_height`` (its xy clamped to the object region), and c_k is the mean of
    those ground points weighted by slot k's cross-attention over the tokens (last decoder
    layer, mean over heads). A slot's 3D centre is then where it looks in the image from the
    first step on; nothing is learned for it. Label-free (the camera is an input of the
    method, the floor plane is the same scene prior as ``fg_zmin``). "attention_slots": the
    same, but the weights are that layer's attention logits normalised over the *slots*
    (every token shared out among the slots, as in Slot Attention), then over the tokens:
    slots compete for image regions, so their centres cannot all sit on the same spot
    (with "attention" they did: measured in docs/notes/cpu_recipe.md). The decoder itself is
    unchanged. "anchored": c_k = a_k + (e / 2) tanh(Linear(s_k)), the learned map of
    "learned" as an offset (up to e / 2 per axis) from a fixed anchor a_k per foreground
    slot: the K-1 anchors lie on a sunflower (Fibonacci) disk of radius 0.6 e at height
    ``centre_height``. With "learned", the centres of every slot can drift onto one spot
    (measured: seed 1 of the recipe ended with all 7 centres within ~0.2 units of each
    other, and one slot took every object); anchors keep them spread while the offsets
    follow the image. cpu recipe lever."""
    centre_focal: float = 35.0 / 32.0
    """Input camera focal length / image width for ``slot_centre="attention"`` (the
    generator's 35 mm lens on a 32 mm sensor; principal point at the image centre)."""
    centre_temperature: float = 1.0
    """Temperature of the softmax over slots for ``slot_centre="attention_slots"``
    (logits / T). T < 1 hands each token to fewer slots: at initialisation the logits differ
    little between slots, and with T = 1 every slot gets an even share of every token, so
    every centre sits at the same spot (measured: the centres then hardly move)."""
    centre_height: float = 0.35
    """Height (world z) of the plane the attention rays are cut at (CLEVR object centres lie
    at z = 0.35 or 0.7)."""

    def __post_init__(self) -> None:
        object.__setattr__(self, "enc_blocks", tuple(int(b) for b in self.enc_blocks))
        if self.enc_up_kernel == 3:  # the paper's 3x3: one spelling, so one config key
            object.__setattr__(self, "enc_up_kernel", None)
        for name, form in _TUPLES.items():  # JSON gives a list
            v = getattr(self, name)
            if v is not None:
                if len(v) != form.count(",") + 1:
                    raise ValueError(f"ModelConfig.{name} must be {form}, got {v}")
                object.__setattr__(self, name, tuple(float(x) for x in v))
        _check_choice("composition", self.composition, Composition)
        _check_choice("slot_module", self.slot_module, SlotModule)
        _check_choice("enc_norm", self.enc_norm, EncoderNorm)
        _check_choice("density_act", self.density_act, DensityAct)
        _check_choice("coord_frame", self.coord_frame, CoordFrame)
        _check_choice("slot_centre", self.slot_centre, SlotCentre)
        check(self)

    def to_dict(self) -> dict[str, Any]:
        """Plain JSON-able dict (tuples become lists; :data:`_OMITTED_WHEN_NONE` fields only
        when set)."""
        d = dataclasses.asdict(self)
        d["enc_blocks"] = list(self.enc_blocks)
        for name in _TUPLES:
            if d[name] is not None:
                d[name] = list(d[name])
        for name in _OMITTED_WHEN_NONE:  # off: not written, so keys of earlier runs stay valid
            if d[name] is None:
                del d[name]
        for name in _OMITTED_WHEN_FALSE:
            if d[name] is False:
                del d[name]
        return d

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> ModelConfig:
        """Inverse of :meth:`to_dict`; unknown keys raise ``ValueError`` naming them."""
        names = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(d) - names)
        if unknown:
            raise ValueError(f"ModelConfig.from_dict: unknown keys {unknown}")
        d = dict(d)
        d.setdefault("coord_frame", "world")  # saved before the field existed: world frame
        if "enc_blocks" in d:
            d["enc_blocks"] = tuple(d["enc_blocks"])
        return cls(**d)

    def to_json(self) -> str:
        return json.dumps(self.to_dict(), indent=2, sort_keys=True)

    @classmethod
    def from_json(cls, text: str) -> ModelConfig:
        return cls.from_dict(json.loads(text))

    def replace(self, **changes: Any) -> ModelConfig:
        """A copy with some fields changed (validated again)."""
        return dataclasses.replace(self, **changes)


def _check_choice(name: str, value: object, literal: object) -> None:
    choices = get_args(literal)
    if value not in choices:
        raise ValueError(f"ModelConfig.{name} must be one of {choices}, got {value!r}")


def ramp(progress: float, p0: float, p1: float) -> float:
    """0 before ``p0``, 1 from ``p1`` on, linear in between (a schedule over the run)."""
    if progress <= p0:
        return 0.0
    if progress >= p1:
        return 1.0
    return (progress - p0) / (p1 - p0)


#: Fields whose effect follows the run's progress: ``SVORF.set_progress`` reads these (and
#: ``slot_locality``, the radius ``slot_locality_narrow`` starts from) and no others, which a
#: test checks. Resuming a run under another time budget would replay them
#: (``svorf.checkpoint.check_resumable_budget``).
PROGRESS_FIELDS: tuple[str, ...] = (
    "bg_chroma_fade",
    "slot_locality_narrow",
    "fg_mass",
    "fg_binary",
    "ray_distortion",
    "photo_l1",
)

#: Tuple fields (JSON gives lists) and their form, for checks and messages.
_TUPLES = {
    "bg_chroma_fade": "(p0, p1)",
    "slot_locality_narrow": "(r_end, p0, p1)",
    "fg_mass": "(lambda, p0, p1)",
    "fg_binary": "(lambda, p0, p1)",
    "box_z": "(floor, ceiling)",
    "photo_l1": "(p0, p1)",
    "ray_distortion": "(lambda, p0, p1)",
}

#: Fields read only at evaluation (no effect on training): left out of ``to_dict`` while off.
#: Fields added after runs were cached: written by ``to_dict`` only when set (not None), so
#: a run that leaves them off keeps the key it had before they existed.
_OMITTED_WHEN_NONE = (
    "eval_early_stop",
    "eval_fine_min_weight",
    "eval_mask_rule",
    "bg_pos_freqs_xyz",
    "box_z",
    "bg_chroma_fade",
    "slot_locality_narrow",
    "clip_floor_z",
    "enc_up_kernel",
    "fg_mass",
    "fg_mass_halo",
    "fg_binary",
    "fg_binary_length",
    "photo_l1",
    "ray_distortion",
)
_OMITTED_WHEN_FALSE = (
    "bg_achromatic",
    "clip_floor_front",
    "slot_locality_xy",
    "slot_relative",
    "fg_binary_all",
    "enc_bf16",
    "enc_full_res",
)


@functools.cache
def _cpu_has_native_bf16() -> bool:
    try:
        with open("/proc/cpuinfo") as f:
            flags = next((ln.split(":", 1)[1].split() for ln in f if ln.startswith("flags")), [])
    except OSError:  # not Linux: no way to tell here, so no
        return False
    return bool(set(flags) & {"avx512_bf16", "amx_bf16"})


def bf16_native(device: Any) -> bool:
    """Whether ``device`` computes bfloat16 matmuls natively (``bf16_autocast="auto"``).

    CUDA: ``torch.cuda.is_bf16_supported()``. CPU: the x86 flags ``avx512_bf16`` or
    ``amx_bf16`` (Linux ``/proc/cpuinfo``); elsewhere False (torch would emulate bf16).
    """
    import torch

    dev = torch.device(device)
    if dev.type == "cuda":
        return bool(torch.cuda.is_available() and torch.cuda.is_bf16_supported())
    if dev.type == "cpu":
        return _cpu_has_native_bf16()
    return False


def bf16_autocast_on(setting: bool | str, device: Any) -> bool:
    """Whether ``ModelConfig.bf16_autocast = setting`` runs bf16 autocast on ``device``."""
    return setting is True or (setting == "auto" and bf16_native(device))


def model_config(
    scale: Scale, num_slots: int = 8, image_size: int | None = None, **overrides: Any
) -> ModelConfig:
    """The model of a scale (sizes from the registry, ``svorf.registry.SCALES``).

    Args:
        scale: "paper" = the paper's sizes (ResNet34 + upsampling to 512 channels at 256x256
            input, 128-wide 4-layer object MLPs, 64+128 samples); "cpu" = a ~2.96M-parameter
            model for 64x64 inputs with 16+16 samples inside the scene box and the speed knobs
            that stay within their tolerances (bf16_autocast, slot_keep_mass=0.99); "smoke" = a tiny
            model for tests (forward+backward well under a second at 32x32).
        num_slots: K including the background slot (paper: 8 CLEVR-567, 5 Room-*, 11 packed).
        image_size: encoder input size; default the scale's (256 / 64 / 32 for paper / cpu /
            smoke).
        **overrides: any other ModelConfig field.

    This is the scale's model without a preset or recipe; ``svorf.train_config.run_configs``
    gives what ``svorf train --scale S --preset P`` trains.

    Paper scale counts 49.53M parameters (K=8) against the paper's 48.73M (+1.6%): encoder
    14.95M, slot decoder 12.88M, hypernetwork 21.45M, composition 0.24M. Left open by the
    paper: decoder depth and FFN width (3 layers, 2048; another depth moves the count by
    4.2M a layer), slot width (512), gamma() with the raw input (0.2M), composition width
    (128), the hypernetwork's form (one linear layer).
    """
    if scale not in SCALES:
        raise ValueError(f"model_config: scale must be one of {SCALE_NAMES}, got {scale!r}")
    spec = SCALES[scale]
    base = ModelConfig(**spec.model)
    return base.replace(num_slots=num_slots, image_size=image_size or spec.image_size, **overrides)
