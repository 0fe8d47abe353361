"""Training ray-sampling policies (which pixels a step's rays go through) and their registry.

Where this sits: below ``svorf.data``, whose :class:`~svorf.data.RaySampler` draws each
training batch's pixels with the strategy named by ``TrainConfig.ray_sampling`` (a key
of :data:`RAY_SAMPLING`); ``svorf.train`` checks that name and feeds the
:class:`ErrorMap` of the stateful ``"error_driven"`` strategy. Nothing here knows the
dataset: a strategy sees only the uint8 colours of a scene's candidate target views and
draws flat pixel indices from a ``torch.Generator``.

Strategies (all label-free: only the images' colours enter, training stays
unsupervised): ``"uniform"`` (the paper), ``"object_heavy"`` (half the rays from pixels
far from the image's median colour, :func:`object_heavy_rays`), ``"object_heavy_ring"``
(the same with the salient pixels grown by one, so the floor ring around an object gets
its edge's rate), ``"object_contrast"``
(the same with local contrast, :func:`object_contrast_rays`), ``"object_balanced"`` (half
the rays shared equally among the connected blobs of salient pixels, so a small object gets
as many rays as a large one, :func:`object_balanced_rays`) and ``"error_driven"`` (half
the rays from image tiles in proportion to the model's recent error there,
:class:`ErrorMap`). :func:`register_ray_sampling` adds more.

Glossary: V views, H x W pixels, n rays.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from functools import partial
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

__all__ = [
    "CONTRAST_KERNEL",
    "CONTRAST_THRESHOLD",
    "ERROR_DRIVEN_EMA",
    "ERROR_DRIVEN_FRACTION",
    "ERROR_DRIVEN_INIT",
    "ERROR_DRIVEN_TILE",
    "OBJECT_BALANCED_MIN_BLOB",
    "OBJECT_HEAVY_FRACTION",
    "OBJECT_HEAVY_THRESHOLD",
    "RAY_SAMPLING",
    "SALIENT_RAY_SAMPLING",
    "STATEFUL_RAY_SAMPLING",
    "ErrorMap",
    "RaySamplingFn",
    "blob_weights",
    "contrast_pixels",
    "object_balanced_rays",
    "object_contrast_rays",
    "object_heavy_rays",
    "register_ray_sampling",
    "salient_pixels",
    "uniform_rays",
]

#: A ray-sampling strategy: ``fn(target_rgb, n, generator) -> flat indices``.
#: ``target_rgb`` is uint8 [Vt, H, W, 3] (the scene's candidate target views); the
#: result is int64 [n] indices into ``Vt * H * W``. Strategies must draw all their
#: randomness from ``generator`` (determinism and exact resume).
RaySamplingFn = Callable[[Tensor, int, torch.Generator], Tensor]


def uniform_rays(target_rgb: Tensor, n: int, generator: torch.Generator) -> Tensor:
    """The paper's sampling: ``n`` pixels uniformly (with replacement) over all target views."""
    total = target_rgb.shape[0] * target_rgb.shape[1] * target_rgb.shape[2]
    return torch.randint(0, total, (n,), generator=generator)


#: Defaults of the "object_heavy" strategy (see :func:`object_heavy_rays`).
OBJECT_HEAVY_FRACTION = 0.5
OBJECT_HEAVY_THRESHOLD = 0.1


def salient_pixels(target_rgb: Tensor, threshold: float = OBJECT_HEAVY_THRESHOLD) -> Tensor:
    """Label-free "probably object" mask: colour far from the image's median colour.

    Args:
        target_rgb: uint8 [V, H, W, 3].
        threshold: in [0, 1] colour units; a pixel is salient when any channel differs
            from its view's per-channel median by more than this.

    Returns:
        bool [V, H, W].
    """
    x = target_rgb.reshape(target_rgb.shape[0], -1, 3).float()
    med = x.median(dim=1, keepdim=True).values
    far = ((x - med).abs() > threshold * 255.0).any(dim=-1)
    return far.reshape(target_rgb.shape[:3])


def object_heavy_rays(
    target_rgb: Tensor,
    n: int,
    generator: torch.Generator,
    *,
    fraction: float = OBJECT_HEAVY_FRACTION,
    threshold: float = OBJECT_HEAVY_THRESHOLD,
    grow: int = 0,
) -> Tensor:
    """Label-free object-heavy sampling (no ground-truth masks).

    ``round(fraction * n)`` rays come uniformly (with replacement) from the salient
    pixels of :func:`salient_pixels` over all target views; the rest, or all ``n`` when
    no pixel is salient, come uniformly from every pixel. Objects get more of the gradient
    from the first steps than under uniform sampling, which left an early model on a "mean
    scene" plateau. Measured with ``python -m benchmark.tools.raystats`` on 120 cpu-scale
    CLEVR-567 training scenes: 10.4% of the rays land on objects against 6.1% uniformly
    (most salient pixels are floor shading and the dark band behind the floor).

    ``grow`` pixels (8-connected) are added around the salient pixels before drawing
    (``"object_heavy_ring"``: 1): the salient half then lands on an object's edge and on the
    floor ring beside it at the same rate. Without it the edge gets about 1.9x the ring's
    rays per pixel (``python -m benchmark.tools.raystats``), which pays a model to grow its
    objects into the floor.
    """
    if not 0.0 <= fraction <= 1.0:
        raise ValueError(f"object_heavy fraction must be in [0, 1], got {fraction}")
    if grow < 0:
        raise ValueError(f"object_heavy grow must be >= 0 pixels, got {grow}")
    total = target_rgb.shape[0] * target_rgb.shape[1] * target_rgb.shape[2]
    mask = salient_pixels(target_rgb, threshold)
    if grow:
        k = 2 * grow + 1
        mask = F.max_pool2d(mask[:, None].float(), k, stride=1, padding=grow)[:, 0] > 0
    cand = mask.reshape(-1).nonzero().squeeze(1)
    n_obj = round(fraction * n) if len(cand) else 0
    picked = cand[torch.randint(0, max(len(cand), 1), (n_obj,), generator=generator)]
    rest = torch.randint(0, total, (n - n_obj,), generator=generator)
    return torch.cat([picked, rest])


#: Defaults of the "object_contrast" strategy (see :func:`contrast_pixels`).
CONTRAST_KERNEL = 5
CONTRAST_THRESHOLD = 0.05


def contrast_pixels(
    target_rgb: Tensor, kernel: int = CONTRAST_KERNEL, threshold: float = CONTRAST_THRESHOLD
) -> Tensor:
    """Label-free "probably object" mask by *local* contrast: colour far from the mean of
    the ``kernel x kernel`` window around the pixel (edge-replicated borders).

    Unlike :func:`salient_pixels` (distance from the view's median colour) it finds grey
    objects on a grey floor and ignores smooth floor shading and the dark band behind the
    floor; a small object is almost all edge, so it is salient as a whole. Measured on 20
    cpu-scale CLEVR-567 training scenes (64x64, 128 rays per scene, half from salient
    pixels): 41 of the 128 rays land on objects against 15 with :func:`salient_pixels`.

    Args:
        target_rgb: uint8 [V, H, W, 3].
        kernel: odd window side in pixels.
        threshold: in [0, 1] colour units, on the largest channel difference.

    Returns:
        bool [V, H, W].
    """
    x = target_rgb.permute(0, 3, 1, 2).float() / 255.0
    r = kernel // 2
    mean = torch.nn.functional.avg_pool2d(
        torch.nn.functional.pad(x, (r, r, r, r), mode="replicate"), kernel, 1
    )
    return (x - mean).abs().amax(dim=1) > threshold


def object_contrast_rays(
    target_rgb: Tensor,
    n: int,
    generator: torch.Generator,
    *,
    fraction: float = OBJECT_HEAVY_FRACTION,
) -> Tensor:
    """Label-free object-heavy sampling with the local-contrast rule: like
    :func:`object_heavy_rays` (``round(fraction * n)`` rays uniformly from the salient
    pixels, the rest uniformly from every pixel), but the salient pixels are those of
    :func:`contrast_pixels`. Only the image's colours enter: training stays unsupervised.
    """
    if not 0.0 <= fraction <= 1.0:
        raise ValueError(f"object_contrast fraction must be in [0, 1], got {fraction}")
    total = target_rgb.shape[0] * target_rgb.shape[1] * target_rgb.shape[2]
    cand = contrast_pixels(target_rgb).reshape(-1).nonzero().squeeze(1)
    n_obj = round(fraction * n) if len(cand) else 0
    picked = cand[torch.randint(0, max(len(cand), 1), (n_obj,), generator=generator)]
    rest = torch.randint(0, total, (n - n_obj,), generator=generator)
    return torch.cat([picked, rest])


#: Defaults of the "object_balanced" strategy (see :func:`object_balanced_rays`).
OBJECT_BALANCED_MIN_BLOB = 16


def blob_weights(
    target_rgb: Tensor,
    threshold: float = OBJECT_HEAVY_THRESHOLD,
    min_blob: int = OBJECT_BALANCED_MIN_BLOB,
    power: float = 1.0,
) -> Tensor:
    """Per-pixel drawing weights that share the salient pixels' mass equally among blobs.

    The salient pixels of :func:`salient_pixels` are cut into connected blobs
    (8-connected, per view); a pixel of a blob of ``a`` pixels weighs ``1 / max(a,
    min_blob) ** power``, every other pixel 0. With ``power`` 1 each blob of at least
    ``min_blob`` pixels carries the same total weight, whatever its size, and smaller blobs
    (specks, highlights) carry ``a / min_blob`` of it; with 0.5 a blob's weight grows as the
    square root of its area (0: every salient pixel alike, as :func:`object_heavy_rays`).
    Only the image's colours enter (no masks).

    Args:
        target_rgb: uint8 [V, H, W, 3].
        threshold: the salience threshold of :func:`salient_pixels`.
        min_blob: the blob size (pixels) below which a blob's share shrinks; >= 1.
        power: in [0, 1], how far the blobs' shares are evened out.

    Returns:
        float64 [V, H, W] (0 where nothing is salient).
    """
    if min_blob < 1:
        raise ValueError(f"object_balanced min_blob must be >= 1, got {min_blob}")
    if not 0.0 <= power <= 1.0:
        raise ValueError(f"object_balanced power must be in [0, 1], got {power}")
    from scipy import ndimage  # only this strategy needs it

    salient = salient_pixels(target_rgb, threshold).numpy()
    weights = np.zeros(salient.shape, dtype=np.float64)
    eight = np.ones((3, 3), dtype=bool)
    for v in range(salient.shape[0]):
        labels, n_blobs = ndimage.label(salient[v], structure=eight)
        if n_blobs:
            per_blob = 1.0 / np.maximum(np.bincount(labels.ravel()), min_blob) ** power
            per_blob[0] = 0.0  # label 0: not salient
            weights[v] = per_blob[labels]
    return torch.from_numpy(weights)


def object_balanced_rays(
    target_rgb: Tensor,
    n: int,
    generator: torch.Generator,
    *,
    fraction: float = OBJECT_HEAVY_FRACTION,
    min_blob: int = OBJECT_BALANCED_MIN_BLOB,
    power: float = 1.0,
) -> Tensor:
    """Label-free object-heavy sampling that does not favour large objects.

    ``round(fraction * n)`` rays are drawn (with replacement) with the weights of
    :func:`blob_weights`: a blob is picked uniformly among the salient blobs of all target
    views, then a pixel uniformly inside it; the rest, or all ``n`` when no pixel is
    salient, come uniformly from every pixel. :func:`object_heavy_rays` draws salient
    pixels uniformly, so a blob's rays grow with its area and half of CLEVR-567's objects
    (those under 30 pixels a view at 64x64) get under one ray a step. Measured on 120
    cpu-scale training scenes, 128 rays per scene: rays on objects 26% against 10%, an
    object under 30 pixels 4.4 rays per step against 0.8 (``python -m
    benchmark.tools.raystats``). ``power`` < 1 evens the blobs out only partly (see
    :func:`blob_weights`); the registered ``"object_balanced_sqrt"`` uses 0.5. Not in the
    cpu recipe: at seed 1 both found the small objects the recipe leaves to the background
    but merged them into neighbours' slots, and FG-ARI fell (docs/notes/cpu_recipe.md).
    """
    if not 0.0 <= fraction <= 1.0:
        raise ValueError(f"object_balanced fraction must be in [0, 1], got {fraction}")
    weights = blob_weights(target_rgb, min_blob=min_blob, power=power).reshape(-1)
    n_obj = round(fraction * n) if bool((weights > 0).any()) else 0
    picked = (
        torch.multinomial(weights, n_obj, replacement=True, generator=generator)
        if n_obj
        else torch.zeros(0, dtype=torch.long)
    )
    rest = torch.randint(0, weights.numel(), (n - n_obj,), generator=generator)
    return torch.cat([picked, rest])


#: Defaults of the "error_driven" strategy (see :class:`ErrorMap`).
ERROR_DRIVEN_FRACTION = 0.5
ERROR_DRIVEN_TILE = 4
ERROR_DRIVEN_EMA = 0.5
ERROR_DRIVEN_INIT = 1.0


class ErrorMap:
    """Label-free error-driven ray sampling: the model's recent error per image tile.

    Every view of every training scene is cut into ``tile x tile`` pixel tiles; each tile
    holds an error estimate, initially ``init`` (far above any photometric error of
    colours in [0, 1], so tiles never visited are drawn first: the first sweep covers the
    images like uniform sampling). After every training step :meth:`update` blends the
    mean squared colour error of the rays that fell in a tile into it
    (``e <- (1 - ema) * e + ema * mean``). :meth:`draw` takes ``round(fraction * n)``
    rays from tiles in proportion to their error (a uniform pixel inside the drawn tile)
    and the rest uniformly from every pixel, so no pixel's probability drops to 0.

    Only the rendered colours enter (no masks, depth or counts): training stays
    unsupervised. The state is part of a training checkpoint (:meth:`state_dict`), so a
    resumed run draws the same rays as an uninterrupted one.

    Args:
        n_scenes, n_views, image_hw: the dataset's shape.
        tile: tile side in pixels (tiles at the right/bottom edge may be partial).
        fraction: share of the rays drawn by error.
        ema: weight of a step's error in a tile's estimate, in (0, 1].
        init: initial estimate of every tile.
    """

    def __init__(
        self,
        n_scenes: int,
        n_views: int,
        image_hw: tuple[int, int],
        *,
        tile: int = ERROR_DRIVEN_TILE,
        fraction: float = ERROR_DRIVEN_FRACTION,
        ema: float = ERROR_DRIVEN_EMA,
        init: float = ERROR_DRIVEN_INIT,
    ) -> None:
        if tile < 1:
            raise ValueError(f"ErrorMap: tile must be >= 1 pixel, got {tile}")
        if not 0.0 <= fraction <= 1.0:
            raise ValueError(f"ErrorMap: fraction must be in [0, 1], got {fraction}")
        if not 0.0 < ema <= 1.0:
            raise ValueError(f"ErrorMap: ema must be in (0, 1], got {ema}")
        if not (init > 0 and math.isfinite(init)):
            raise ValueError(f"ErrorMap: init must be a finite value > 0, got {init}")
        self.h, self.w = int(image_hw[0]), int(image_hw[1])
        self.tile, self.fraction, self.ema = int(tile), float(fraction), float(ema)
        self.th, self.tw = -(-self.h // self.tile), -(-self.w // self.tile)
        self.err = torch.full((n_scenes, n_views, self.th * self.tw), float(init))

    def _tile_of(self, pixel: Tensor) -> Tensor:
        """Tile index of flat pixel indices ``y * W + x``."""
        y, x = pixel // self.w, pixel % self.w
        return (y // self.tile) * self.tw + x // self.tile

    def draw(self, scene: int, views: Tensor, n: int, generator: torch.Generator) -> Tensor:
        """``n`` flat indices into ``len(views) * H * W`` (the ray-sampling contract).

        Args:
            scene: dataset position.
            views: int64 [Vt] candidate view indices of the scene.
            n: rays to draw.
        """
        hw = self.h * self.w
        n_err = round(self.fraction * n)
        weights = self.err[scene, views].reshape(-1).clamp_min(1e-12)  # [Vt * T]
        picked = torch.multinomial(weights, n_err, replacement=True, generator=generator)
        vi, t = picked // (self.th * self.tw), picked % (self.th * self.tw)
        ty, tx = t // self.tw, t % self.tw
        # a uniform pixel of the tile (partial edge tiles: clamp to the image)
        dy = torch.randint(0, self.tile, (n_err,), generator=generator)
        dx = torch.randint(0, self.tile, (n_err,), generator=generator)
        y = (ty * self.tile + dy).clamp_max(self.h - 1)
        x = (tx * self.tile + dx).clamp_max(self.w - 1)
        rest = torch.randint(0, len(views) * hw, (n - n_err,), generator=generator)
        return torch.cat([vi * hw + y * self.w + x, rest])

    @torch.no_grad()
    def update(self, scenes: Tensor, views: Tensor, pixels: Tensor, sq_err: Tensor) -> None:
        """Blend the rays' errors into their tiles.

        Args:
            scenes: int64 [B] dataset positions of the batch rows.
            views: int64 [B, R] view of each ray (``RayBatch.target_view``).
            pixels: int64 [B, R] flat pixel of each ray (``RayBatch.target_pixel``).
            sq_err: [B, R] squared colour error of each ray (mean over channels).
        """
        sq_err = sq_err.detach().float().cpu()
        if not bool(torch.isfinite(sq_err).all()):
            return  # a diverging step is reported by the trainer; keep the estimates
        n_tiles = self.th * self.tw
        flat = (
            scenes.cpu().reshape(-1, 1) * self.err.shape[1] + views.cpu()
        ) * n_tiles + self._tile_of(pixels.cpu())
        flat = flat.reshape(-1)
        e = self.err.view(-1)
        sums = torch.zeros_like(e).index_add_(0, flat, sq_err.reshape(-1))
        cnt = torch.zeros_like(e).index_add_(0, flat, torch.ones(flat.shape[0]))
        hit = cnt > 0
        e[hit] = (1.0 - self.ema) * e[hit] + self.ema * sums[hit] / cnt[hit]

    def state_dict(self) -> dict[str, Any]:
        """``{"err": float32 [N, V, tiles] copy of the estimates, "tile": tile side}``
        (saved in training checkpoints as ``"error_map"``)."""
        return {"err": self.err.clone(), "tile": self.tile}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore the estimates of :meth:`state_dict` (same dataset shape and tile).

        Raises:
            ValueError: the saved map does not fit this dataset or tile size.
        """
        err = state["err"]
        if tuple(err.shape) != tuple(self.err.shape) or int(state["tile"]) != self.tile:
            raise ValueError(
                f"ErrorMap: saved map {tuple(err.shape)} (tile {state['tile']}) does not fit "
                f"this dataset {tuple(self.err.shape)} (tile {self.tile})"
            )
        self.err.copy_(err)


#: Registry of ray-sampling strategies by name (``TrainConfig.ray_sampling``).
#: ``"error_driven"`` is stateful: ``svorf.data.RaySampler`` draws it from its :class:`ErrorMap`
#: (the trainer feeds the map); called as a plain function it is uniform sampling.
RAY_SAMPLING: dict[str, RaySamplingFn] = {
    "uniform": uniform_rays,
    "object_heavy": object_heavy_rays,
    "object_heavy_ring": partial(object_heavy_rays, grow=1),
    "object_contrast": object_contrast_rays,
    "object_balanced": object_balanced_rays,
    "object_balanced_sqrt": partial(object_balanced_rays, power=0.5),
    "error_driven": uniform_rays,
}
#: Strategies that need an :class:`ErrorMap` fed with each step's per-ray errors.
STATEFUL_RAY_SAMPLING = frozenset({"error_driven"})
#: Strategies that draw a share of the rays (keyword ``fraction``, default
#: :data:`OBJECT_HEAVY_FRACTION`) from salient pixels and the rest uniformly; with
#: ``fraction=0`` they are uniform sampling (``TrainConfig.salient_fade`` fades it).
SALIENT_RAY_SAMPLING = frozenset(
    {
        "object_heavy",
        "object_heavy_ring",
        "object_contrast",
        "object_balanced",
        "object_balanced_sqrt",
    }
)


def register_ray_sampling(name: str, fn: RaySamplingFn) -> None:
    """Add a strategy to :data:`RAY_SAMPLING` (e.g. object-heavy or error-driven)."""
    if name in RAY_SAMPLING:
        raise ValueError(f"ray sampling strategy {name!r} is already registered")
    RAY_SAMPLING[name] = fn
