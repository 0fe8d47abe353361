"""Multi-view scene dataset with rays computed from its cameras, and the training ray sampler.

Where this sits: ``dataset on disk -> svorf.data -> model``. :class:`MultiViewDataset`
reads a generated split folder (the :mod:`scenefmt` contract; a plain uORF-layout folder
through ``scenefmt.uorf``) once into memory, optionally resized to the training
resolution, and computes the rays of any pixel from the cameras. :class:`RaySampler`
draws the training batches of the paper's setup (one input view per scene, ``R`` random
rays from the scene's other views), the pixels picked by a strategy of
:data:`RAY_SAMPLING` (``svorf.ray_sampling``: ``"uniform"`` = paper; label-free
``"object_heavy"``, ``"object_contrast"`` and ``"error_driven"`` with its
:class:`ErrorMap`). Unreadable folders raise :class:`DatasetError` (``scenefmt.errors``).
The public names of ``svorf.ray_sampling``, ``DatasetError``, the uORF reader's constants and
``scenefmt.dataset_fingerprint`` stay importable from here.

Conventions (all tensors are float32 unless said otherwise):

- cameras: ``cam_to_world`` [4, 4] with OpenCV axes (x right, y down, z forward),
  z-up world, world units; ``K`` [3, 3] in pixels of the *loaded* resolution, with
  pixel ``(u, v)`` covering ``[u, u+1) x [v, v+1)`` (its centre is ``(u+0.5, v+0.5)``);
- rays: ``rays_o`` is the camera centre, ``rays_d`` the *unit* world direction
  through the pixel centre; the distance ``t`` along it relates to the planar depth
  by ``depth_z = t * z_scale`` where ``z_scale`` is the camera-z component of the unit
  direction (``<= 1``, equal to 1 on the optical axis);
- ``depth_z``: planar depth (camera z), world units, ``inf`` (or ``nan``) where no
  surface was hit or the dataset has no depth;
- ``instances``: int64, 0 = background, ``k`` = object ``k`` of the scene JSON.

Resizing (``image_size``): images are area-averaged (``F.interpolate(mode="area")``,
re-quantised to 8 bits),
instance ids and depth take the source pixel under the new pixel's centre (nearest;
averaging ids or depths across an edge would invent values), and ``K`` is rescaled
as ``K' = diag(W'/W, H'/H, 1) @ K``. Because pixel edges lie on integer coordinates,
scaling the continuous image plane maps pixel centres to pixel centres and needs no
half-pixel shift. Only down-sampling is allowed.

Memory: the images are held in memory as uint8 (3 bytes per pixel); the ground truth
(uint8 ids, float32 depth: 5 bytes per pixel) only when loaded with ``truth=True``, which
training does not do. Rays are not cached: a training batch computes its R rays per scene
from the cameras (:meth:`MultiViewDataset.rays`), and ``dataset[i]`` computes the scene's
per-pixel rays on access. A 4-view 64x64 scene takes 49 KB for training, 131 KB with
truth (a per-pixel ray cache added 262 KB more).

Glossary: B scenes, V views, H x W pixels, R rays per scene, K slots.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import dataclass, replace
from functools import partial
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from scenefmt import (
    LUMA_REC601,
    DatasetError,
    Manifest,
    SceneRecord,
    SplitLayout,
    dataset_fingerprint,
    missing_file,
    read_depth_exr,
    read_file,
    read_instances,
    read_json,
    read_rgb,
)
from scenefmt.uorf import (
    UORF_EXCLUDED_SUFFIXES,
    UORF_FOV_DEG,
    read_uorf_scene,
    uorf_view_files,
)
from svorf.ray_sampling import (
    CONTRAST_KERNEL,
    CONTRAST_THRESHOLD,
    ERROR_DRIVEN_EMA,
    ERROR_DRIVEN_FRACTION,
    ERROR_DRIVEN_INIT,
    ERROR_DRIVEN_TILE,
    OBJECT_HEAVY_FRACTION,
    OBJECT_HEAVY_THRESHOLD,
    RAY_SAMPLING,
    SALIENT_RAY_SAMPLING,
    STATEFUL_RAY_SAMPLING,
    ErrorMap,
    RaySamplingFn,
    contrast_pixels,
    object_contrast_rays,
    object_heavy_rays,
    register_ray_sampling,
    salient_pixels,
)

# With the names re-exported from svorf.ray_sampling and scenefmt (their old home).
__all__ = [
    "CONTRAST_KERNEL",
    "CONTRAST_THRESHOLD",
    "ERROR_DRIVEN_EMA",
    "ERROR_DRIVEN_FRACTION",
    "ERROR_DRIVEN_INIT",
    "ERROR_DRIVEN_TILE",
    "OBJECT_HEAVY_FRACTION",
    "OBJECT_HEAVY_THRESHOLD",
    "RAY_SAMPLING",
    "STATEFUL_RAY_SAMPLING",
    "UORF_EXCLUDED_SUFFIXES",
    "UORF_FOV_DEG",
    "DatasetError",
    "ErrorMap",
    "MultiViewDataset",
    "RayBatch",
    "RaySampler",
    "RaySamplingFn",
    "SceneViews",
    "contrast_pixels",
    "dataset_fingerprint",
    "gray_some_scenes",
    "object_contrast_rays",
    "object_heavy_rays",
    "pixel_rays",
    "rays_at",
    "register_ray_sampling",
    "resize_intrinsics",
    "salient_pixels",
]

# --------------------------------------------------------------------------- rays


def rays_at(K: Tensor, cam_to_world: Tensor, u: Tensor, v: Tensor) -> tuple[Tensor, Tensor]:
    """Rays through pixel centres ``(u, v)`` (pixel columns / rows, integers) of views.

    Element-wise float64 maths (no matrix products whose summation order depends on the
    batch shape), so a ray is bit-identical whether computed for one pixel or the whole
    image; returned as float32. :func:`pixel_rays` is this on the full pixel grid.

    Args:
        K: [..., 3, 3] intrinsics in pixels (pixel centres at ``u + 0.5``).
        cam_to_world: [..., 4, 4], OpenCV axes, the same leading shape as ``K``.
        u, v: integer pixel coordinates, broadcastable against the leading shape of ``K``
            (e.g. ``K`` [V, 1, 1, 3, 3] with ``u``, ``v`` [H, W]).

    Returns:
        ``(rays_d [..., 3] unit world directions, z_scale [...] camera-z of the unit
        direction)``, with the broadcast shape of ``u``, ``v`` and ``K``'s leading dims.
    """
    return _rays_from_kinv(torch.linalg.inv(K.double()), cam_to_world, u, v)


def _rays_from_kinv(
    kinv: Tensor, cam_to_world: Tensor, u: Tensor, v: Tensor, offset: Tensor | None = None
):
    """:func:`rays_at` with ``K^-1`` (float64) given: the dataset inverts each K once.
    ``offset`` [..., 2] (pixels, column then row) moves each ray off its pixel centre."""
    rot = cam_to_world.double()[..., :3, :3]
    uc, vc = u.double() + 0.5, v.double() + 0.5
    if offset is not None:
        uc, vc = uc + offset[..., 0].double(), vc + offset[..., 1].double()
    # d_cam = K^-1 [u, v, 1]; K^-1 is upper triangular for every K a camera writes, but
    # the full product costs nothing and keeps skewed or odd intrinsics right.
    d_cam = torch.stack(
        [kinv[..., i, 0] * uc + kinv[..., i, 1] * vc + kinv[..., i, 2] for i in range(3)], dim=-1
    )
    d_cam = d_cam / d_cam.norm(dim=-1, keepdim=True)
    d = torch.stack(
        [
            rot[..., i, 0] * d_cam[..., 0]
            + rot[..., i, 1] * d_cam[..., 1]
            + rot[..., i, 2] * d_cam[..., 2]
            for i in range(3)
        ],
        dim=-1,
    )
    d = d / d.norm(dim=-1, keepdim=True)  # exact rotations keep it unit
    return d.float(), d_cam[..., 2].float()


def pixel_rays(
    K: Tensor, cam_to_world: Tensor, height: int, width: int
) -> tuple[Tensor, Tensor, Tensor]:
    """Rays through every pixel centre of a batch of views.

    Computed in float64 and returned as float32 (:func:`rays_at` on the full grid).

    Args:
        K: [V, 3, 3] intrinsics in pixels (pixel centres at ``u + 0.5``).
        cam_to_world: [V, 4, 4], OpenCV axes.
        height, width: image size in pixels.

    Returns:
        ``(rays_o [V, 3], rays_d [V, H, W, 3] unit world directions,
        z_scale [V, H, W] camera-z of the unit direction)``.
    """
    if K.ndim != 3 or K.shape[1:] != (3, 3):
        raise ValueError(f"K must be [V, 3, 3], got {tuple(K.shape)}")
    if cam_to_world.shape != (K.shape[0], 4, 4):
        raise ValueError(
            f"cam_to_world must be [{K.shape[0]}, 4, 4], got {tuple(cam_to_world.shape)}"
        )
    v, u = torch.meshgrid(torch.arange(height), torch.arange(width), indexing="ij")
    rays_d, z_scale = rays_at(K[:, None, None], cam_to_world[:, None, None], u, v)
    return cam_to_world[:, :3, 3].float(), rays_d, z_scale


def resize_intrinsics(K: Tensor, src_hw: tuple[int, int], dst_hw: tuple[int, int]) -> Tensor:
    """``K`` [..., 3, 3] for images resized from ``src_hw`` to ``dst_hw`` (H, W).

    With pixel edges on integer coordinates, resizing scales the image plane:
    ``fx, cx *= W'/W`` and ``fy, cy *= H'/H`` (skew scales with x).
    """
    sx = dst_hw[1] / src_hw[1]
    sy = dst_hw[0] / src_hw[0]
    S = torch.tensor([[sx, 0.0, 0.0], [0.0, sy, 0.0], [0.0, 0.0, 1.0]], dtype=K.dtype)
    return S @ K


def _nearest_index(src: int, dst: int) -> Tensor:
    """Source pixel under each destination pixel centre: ``floor((i + 0.5) * src / dst)``."""
    idx = torch.floor((torch.arange(dst, dtype=torch.float64) + 0.5) * (src / dst)).long()
    return idx.clamp_(0, src - 1)


# --------------------------------------------------------------------------- dataset


@dataclass(frozen=True)
class SceneViews:
    """All views of one scene, as returned by ``MultiViewDataset[i]``.

    Attributes:
        scene: the scene number in the split (``sc%04d`` of the file names).
        images: [V, 3, H, W] float32 in [0, 1] (sRGB values as stored).
        K: [V, 3, 3] intrinsics at this resolution.
        cam_to_world: [V, 4, 4], OpenCV axes.
        instances: [V, H, W] int64, 0 = background; None for a dataset loaded with
            ``truth=False`` (training data: no ground truth in memory).
        depth_z: [V, H, W] planar depth, world units, inf/nan = none; None with
            ``truth=False``.
        rays_o: [V, H, W, 3] camera centres (an expanded view, no copy).
        rays_d: [V, H, W, 3] unit world directions through pixel centres.
        z_scale: [V, H, W] camera-z of ``rays_d``: ``depth_z = t * z_scale``.
    """

    scene: int
    images: Tensor
    K: Tensor
    cam_to_world: Tensor
    instances: Tensor | None
    depth_z: Tensor | None
    rays_o: Tensor
    rays_d: Tensor
    z_scale: Tensor


def _as_hw(size: int | Sequence[int] | None) -> tuple[int, int] | None:
    if size is None:
        return None
    if isinstance(size, int):
        return (size, size)
    size = tuple(int(s) for s in size)
    if len(size) != 2:
        raise ValueError(f"image_size must be an int or (H, W), got {size}")
    return size  # type: ignore[return-value]


class MultiViewDataset(torch.utils.data.Dataset):
    """A generated split folder, in memory; rays are computed from the cameras on access.

    Args:
        root: the split folder (e.g. ``data/clevr567/train``).
        image_size: training resolution, an int (square) or ``(H, W)``; ``None`` keeps
            the stored resolution. Must not exceed it (only down-sampling).
        max_scenes: load only the first ``max_scenes`` scenes (sorted by scene number).
        uorf_layout: read a plain uORF-layout folder (PNG views, ``_RT.txt``, ``_mask.png``;
            no manifest, JSON, depth or intrinsics) instead of our format. Assumptions
            (uORF's loader and projection, which store none of this): view images are the
            ``*.png`` files directly in the folder without a known suffix, grouped into
            scenes by the ``sc%04d`` in their names and ordered by name; every scene has
            the same number of views; ``K`` has its principal point at the image centre
            and the field of view ``uorf_fov_deg``; ``{stem}_RT.txt`` is camera-to-world
            with axes ``uorf_axes``; ``{stem}_depth.npy`` (optional) holds planar z, else
            depth is NaN; instance ids come from ``{stem}_mask.png`` by uORF's
            second-lowest-grey-level background rule (see
            ``scenefmt.uorf.uorf_instance_ids``), all background when the mask is
            absent. The folder fingerprint hashes the ``_RT.txt`` files.
        uorf_fov_deg: field of view (x, y) or one value for both, in degrees, used to
            build ``K`` for uORF-layout folders. Default: uORF's own projection.
        scenes: load only these scene numbers (``sc%04d``; applied before ``max_scenes``),
            e.g. to render one scene of a large split without reading the rest.
        uorf_axes: camera axes of the ``_RT.txt`` matrices of a uORF-layout folder.
            ``"opencv"`` (default): uORF's ``models/projection.py`` maps pixel column,
            pixel row and positive depth straight through ``cam2world``, i.e. x right,
            y down, z forward; ``"opengl"`` (x right, y up, z backward, Blender's
            ``matrix_world``) converts with ``@ diag(1, -1, -1, 1)``.
        truth: also load the ground truth (instance ids and depth). Training passes
            ``False``: the ids and depth files are not read at all (no depth EXR decoding,
            less memory), so nothing of the ground truth can reach an unsupervised
            training run; ``SceneViews.instances`` / ``depth_z`` are then None.

    Raises:
        DatasetError: a one-line message naming the missing/bad file and the fix.

    Example:
        >>> ds = MultiViewDataset("data/clevr567/train", image_size=64)
        >>> sv = ds[0]; sv.images.shape
        torch.Size([4, 3, 64, 64])
    """

    def __init__(
        self,
        root: str | os.PathLike,
        image_size: int | Sequence[int] | None = None,
        max_scenes: int | None = None,
        uorf_layout: bool = False,
        *,
        uorf_fov_deg: float | tuple[float, float] = UORF_FOV_DEG,
        uorf_axes: str = "opencv",
        scenes: Sequence[int] | None = None,
        truth: bool = True,
    ) -> None:
        self.root = Path(root)
        if not self.root.is_dir():
            raise DatasetError(f"{self.root}: not a directory (expected a generated split folder)")
        if max_scenes is not None and max_scenes < 1:
            raise ValueError(f"max_scenes must be >= 1 or None, got {max_scenes}")
        if uorf_axes not in ("opencv", "opengl"):
            raise ValueError(f"uorf_axes must be 'opencv' or 'opengl', got {uorf_axes!r}")
        self.uorf_layout = uorf_layout
        self.truth = bool(truth)
        self.manifest: Manifest | None = None  # None for uORF-layout folders
        self._only = None if scenes is None else {int(x) for x in scenes}
        if uorf_layout:
            loaded = self._load_uorf(max_scenes, uorf_fov_deg, uorf_axes)
        else:
            loaded = self._load_ours(max_scenes)
        scenes, rgb, ids, depth, K, c2w = loaded
        self.scene_ids: list[int] = scenes
        src_hw = (rgb.shape[2], rgb.shape[3])
        dst_hw = _as_hw(image_size) or src_hw
        if dst_hw[0] > src_hw[0] or dst_hw[1] > src_hw[1]:
            raise DatasetError(
                f"{self.root}: image_size {dst_hw} exceeds the stored resolution {src_hw}; "
                f"only down-sampling is supported (regenerate with a larger --resolution)"
            )
        if dst_hw != src_hw:
            rgb, ids, depth = self._resize(rgb, ids, depth, dst_hw)
            K = resize_intrinsics(K, src_hw, dst_hw)
        self.image_hw: tuple[int, int] = dst_hw
        self.source_hw: tuple[int, int] = src_hw
        self.n_views: int = rgb.shape[1]
        self._rgb = rgb  # uint8 [N, V, H, W, 3]
        self._ids = ids  # uint8 [N, V, H, W], None without truth
        self._depth = depth  # float32 [N, V, H, W], None without truth
        # Cameras in float64 (rays are computed from these, exactly as before they were
        # cached) and float32 (what the model receives). No per-pixel ray cache: it took
        # 16 of every 25 bytes per pixel, and a batch needs only R rays per scene.
        self._K64 = K.double()  # [N, V, 3, 3]
        self._Kinv64 = torch.linalg.inv(self._K64)  # per batch: no inverse on the hot path
        self._c2w64 = c2w.double()  # [N, V, 4, 4]
        self._K = K.float()
        self._c2w = c2w.float()
        self._rays_o = self._c2w64[:, :, :3, 3].float()  # [N, V, 3]
        self._fingerprint: str | None = None

    # ---------------------------------------------------------------- loading

    def _select(self, scenes: list[int], max_scenes: int | None) -> list[int]:
        if self._only is not None:
            missing = sorted(self._only - set(scenes))
            if missing:
                raise DatasetError(
                    f"{self.root}: no scene sc{missing[0]:04d} (the split holds "
                    f"{len(scenes)} scenes, sc{scenes[0]:04d}..sc{scenes[-1]:04d})"
                )
            scenes = [x for x in scenes if x in self._only]
        return scenes if max_scenes is None else scenes[:max_scenes]

    def _load_ours(self, max_scenes: int | None):
        manifest_path = self.root / "manifest.json"
        if not manifest_path.is_file():
            raise missing_file(manifest_path, self.root)
        try:
            raw = read_json(manifest_path)
        except (OSError, ValueError) as e:
            raise DatasetError(
                f"{manifest_path}: unreadable JSON ({e}); run `generate verify {self.root}`"
            ) from e
        try:
            self.manifest = Manifest.from_json(raw)
        except ValueError as e:
            raise DatasetError(f"{manifest_path}: {e}; run `generate verify {self.root}`") from e
        n_views = self.manifest.n_views
        layout = SplitLayout(self.root, n_views=n_views)
        scenes = layout.scene_indices()
        if not scenes:
            raise DatasetError(
                f"{self.root}: no sc%04d.json scene files - not a generated split folder "
                f"(run `generate verify {self.root}`)"
            )
        if len(scenes) < self.manifest.n_scenes:
            expected = set(range(self.manifest.n_scenes))
            first = min(expected - set(scenes), default=None)
            if first is not None:
                raise missing_file(layout.scene_json(first), self.root)
        scenes = self._select(scenes, max_scenes)
        rgb, ids, depth, Ks, c2ws = [], [], [], [], []
        for s in scenes:
            # Without truth, the ground-truth files (ids, depth, uORF mask) need not exist.
            gt = set() if self.truth else {
                f(s, v) for v in range(n_views)
                for f in (layout.instances, layout.depth, layout.mask)
            }  # fmt: skip
            for p in layout.scene_files(s):
                if p not in gt and not p.is_file():
                    raise missing_file(p, self.root)
            jpath = layout.scene_json(s)
            raw = read_file(read_json, jpath, self.root)
            try:
                meta = SceneRecord.from_json(raw)
            except ValueError as e:
                raise DatasetError(f"{jpath}: not a valid scene record ({e})") from e
            if meta.camera_convention != "opencv":
                raise DatasetError(
                    f"{jpath}: camera_convention {meta.camera_convention!r} is not 'opencv'"
                )
            if meta.depth != "planar_z":
                raise DatasetError(f"{jpath}: depth convention {meta.depth!r} is not 'planar_z'")
            if meta.n_views != n_views:
                raise DatasetError(
                    f"{jpath}: expected {n_views} entries in 'views', got {meta.n_views}"
                )
            s_rgb, s_ids, s_depth, s_K, s_c2w = [], [], [], [], []
            for view, vm in enumerate(meta.views):
                try:
                    Kv = np.asarray(vm.K, dtype=np.float64)
                    Tv = np.asarray(vm.cam_to_world, dtype=np.float64)
                except (TypeError, ValueError) as e:
                    raise DatasetError(
                        f"{jpath}: view {view} lacks a valid K / cam_to_world ({e})"
                    ) from e
                if vm.image and Path(vm.image).name != layout.rgb(s, view).name:
                    raise DatasetError(
                        f"{jpath}: view {view} image {vm.image!r} does not match the "
                        f"layout name {layout.rgb(s, view).name!r}"
                    )
                img = read_file(read_rgb, layout.rgb(s, view), self.root)
                s_rgb.append(img)
                if self.truth:
                    inst = read_file(read_instances, layout.instances(s, view), self.root)
                    dz = read_file(read_depth_exr, layout.depth(s, view), self.root)
                    if inst.shape != img.shape[:2] or dz.shape != img.shape[:2]:
                        raise DatasetError(
                            f"{layout.rgb(s, view)}: image {img.shape[:2]}, instances "
                            f"{inst.shape} and depth {dz.shape} sizes differ "
                            f"(run `generate verify {self.root}`)"
                        )
                    s_ids.append(inst)
                    s_depth.append(dz)
                s_K.append(Kv)
                s_c2w.append(Tv)
            rgb.append(np.stack(s_rgb))
            if self.truth:
                ids.append(np.stack(s_ids))
                depth.append(np.stack(s_depth))
            Ks.append(np.stack(s_K))
            c2ws.append(np.stack(s_c2w))
        return self._assemble(scenes, rgb, ids, depth, Ks, c2ws)

    def _assemble(self, scenes, rgb, ids, depth, Ks, c2ws):
        """The loaders' per-scene lists as stacked tensors (ids/depth None without truth)."""
        shapes = {a.shape for a in rgb}
        if len(shapes) != 1:
            raise DatasetError(f"{self.root}: scenes have different image sizes {sorted(shapes)}")
        return (
            scenes,
            torch.from_numpy(np.stack(rgb)),
            torch.from_numpy(np.stack(ids)) if self.truth else None,
            torch.from_numpy(np.stack(depth).astype(np.float32)) if self.truth else None,
            torch.from_numpy(np.stack(Ks)),
            torch.from_numpy(np.stack(c2ws)),
        )

    def _load_uorf(self, max_scenes: int | None, fov_deg, axes: str):
        by_scene = uorf_view_files(self.root)
        scenes = self._select(sorted(by_scene), max_scenes)
        counts = {len(by_scene[s]) for s in scenes}
        if len(counts) != 1:
            raise DatasetError(f"{self.root}: scenes have different view counts {sorted(counts)}")
        rgb, ids, depth, Ks, c2ws = [], [], [], [], []
        for s in scenes:
            sc = read_uorf_scene(self.root, s, by_scene[s], fov_deg, axes, self.truth)
            rgb.append(sc.rgb)
            if self.truth:
                ids.append(sc.ids)
                depth.append(sc.depth)
            Ks.append(sc.K)
            c2ws.append(sc.cam_to_world)
        return self._assemble(scenes, rgb, ids, depth, Ks, c2ws)

    @staticmethod
    def _resize(rgb: Tensor, ids: Tensor, depth: Tensor, hw: tuple[int, int]):
        n, v, h, w, _ = rgb.shape
        x = rgb.reshape(n * v, h, w, 3).permute(0, 3, 1, 2).float()
        x = F.interpolate(x, size=hw, mode="area")
        rgb = x.round().clamp(0, 255).to(torch.uint8).permute(0, 2, 3, 1).reshape(n, v, *hw, 3)
        if ids is None:  # loaded without truth
            return rgb, None, None
        iy, ix = _nearest_index(h, hw[0]), _nearest_index(w, hw[1])
        ids = ids[:, :, iy][:, :, :, ix].contiguous()
        depth = depth[:, :, iy][:, :, :, ix].contiguous()
        return rgb, ids, depth

    # ---------------------------------------------------------------- access

    def __len__(self) -> int:
        return self._rgb.shape[0]

    def __getitem__(self, i: int) -> SceneViews:
        if not -len(self) <= i < len(self):
            raise IndexError(f"scene position {i} out of range for {len(self)} scenes")
        v, (h, w) = self.n_views, self.image_hw
        _, rays_d, z_scale = pixel_rays(self._K64[i], self._c2w64[i], h, w)
        return SceneViews(
            scene=self.scene_ids[i],
            images=self.images(i),
            K=self._K[i],
            cam_to_world=self._c2w[i],
            instances=None if self._ids is None else self._ids[i].long(),
            depth_z=None if self._depth is None else self._depth[i],
            rays_o=self._rays_o[i][:, None, None, :].expand(v, h, w, 3),
            rays_d=rays_d,
            z_scale=z_scale,
        )

    def rays(
        self, i: int, views: Tensor, pixels: Tensor, offset: Tensor | None = None
    ) -> tuple[Tensor, Tensor]:
        """``(rays_o [R, 3], rays_d [R, 3])`` of scene position ``i`` through flat pixel
        indices ``pixels`` [R] (``row * W + column``) of ``views`` [R]: the same values as
        ``self[i].rays_d[views, row, column]``, computed for these pixels only; with
        ``offset`` [R, 2] (pixels, column then row) through those points off the centres."""
        w = self.image_hw[1]
        kinv, c2w = self._Kinv64[i][views], self._c2w64[i][views]
        rays_d, _ = _rays_from_kinv(kinv, c2w, pixels % w, pixels // w, offset)
        return self._rays_o[i][views], rays_d

    def images(self, i: int, views: Tensor | Sequence[int] | None = None) -> Tensor:
        """[V, 3, H, W] float32 in [0, 1] of scene position ``i`` (optionally some views)."""
        x = self._rgb[i] if views is None else self._rgb[i][torch.as_tensor(views)]
        return x.permute(0, 3, 1, 2).float().div_(255.0)

    @property
    def fingerprint(self) -> str:
        """:func:`dataset_fingerprint` of the folder (computed once)."""
        if self._fingerprint is None:
            self._fingerprint = dataset_fingerprint(self.root)
        return self._fingerprint

    @property
    def preset(self) -> str | None:
        """The manifest's preset (``None`` for uORF-layout folders)."""
        return None if self.manifest is None else self.manifest.preset


@dataclass(frozen=True)
class RayBatch:
    """One training batch: an input view per scene and target rays.

    Attributes:
        scenes: [B] int64 dataset positions.
        input_view: [B] int64 view index of each input image.
        images: [B, 3, H, W] float32 in [0, 1], the input views.
        rays_o: [B, R, 3] ray origins (world).
        rays_d: [B, R, 3] unit ray directions (world).
        target_rgb: [B, R, 3] float32 in [0, 1].
        target_view: [B, R] int64 view index of each ray.
        target_pixel: [B, R] int64 flat pixel index ``v * W + u`` of each ray.
        input_c2w: [B, 4, 4] float32 camera-to-world of each input view (the model's
            ``input_c2w``: the frame of ``ModelConfig.coord_frame``).
    """

    scenes: Tensor
    input_view: Tensor
    images: Tensor
    rays_o: Tensor
    rays_d: Tensor
    target_rgb: Tensor
    target_view: Tensor
    target_pixel: Tensor
    input_c2w: Tensor

    def to(self, device: torch.device | str) -> RayBatch:
        """The batch with every tensor on ``device``."""
        return RayBatch(**{k: getattr(self, k).to(device) for k in self.__dataclass_fields__})


class RaySampler:
    """Draws training batches: one input view and ``R`` target rays per scene.

    With ``nvs=True`` (the paper's novel-view setup) the input view is uniform over the
    scene's views and the rays come from the *other* views; with ``nvs=False`` the rays
    come from the input view itself. Which pixels is decided by the strategy
    ``ray_sampling`` (a name in :data:`RAY_SAMPLING`; ``"uniform"`` = the paper).

    Args:
        dataset: the in-memory dataset.
        rays_per_scene: R (paper: 64).
        nvs: novel-view setup (``ModelConfig.nvs``).
        ray_sampling: strategy name.
        error_map: the :class:`ErrorMap` of ``"error_driven"`` (shared by the samplers of
            one run); made here when None.
        input_size: the encoder's input side (``TrainConfig.target_size``): the input view
            is area-averaged down to it from the dataset's resolution, from which the target
            rays still come. None = the dataset's resolution for both.
    """

    def __init__(
        self,
        dataset: MultiViewDataset,
        rays_per_scene: int = 64,
        *,
        nvs: bool = True,
        ray_sampling: str = "uniform",
        error_map: ErrorMap | None = None,
        input_size: int | None = None,
    ) -> None:
        if input_size is not None and not 1 <= input_size <= min(dataset.image_hw):
            raise ValueError(
                f"input_size must be in [1, {min(dataset.image_hw)}] (the dataset's "
                f"resolution), got {input_size}"
            )
        if rays_per_scene < 1:
            raise ValueError(f"rays_per_scene must be >= 1, got {rays_per_scene}")
        if ray_sampling not in RAY_SAMPLING:
            raise ValueError(
                f"unknown ray_sampling {ray_sampling!r}; choose from {sorted(RAY_SAMPLING)}"
            )
        if nvs and dataset.n_views < 2:
            raise ValueError(
                f"nvs=True needs >= 2 views per scene, the dataset has {dataset.n_views}"
            )
        self.dataset = dataset
        self.rays_per_scene = rays_per_scene
        self.nvs = nvs
        self.ray_sampling = ray_sampling
        self.input_size = input_size
        self._fn = RAY_SAMPLING[ray_sampling]
        self.error_map: ErrorMap | None = None
        if ray_sampling in STATEFUL_RAY_SAMPLING:
            self.error_map = error_map or ErrorMap(len(dataset), dataset.n_views, dataset.image_hw)

    def sample_scenes(self, batch_scenes: int, generator: torch.Generator) -> Tensor:
        """[B] distinct scene positions (with replacement only if B > len(dataset))."""
        n = len(self.dataset)
        if batch_scenes <= n:
            return torch.randperm(n, generator=generator)[:batch_scenes]
        return torch.randint(0, n, (batch_scenes,), generator=generator)

    def sample(
        self,
        scenes: Tensor | Sequence[int],
        generator: torch.Generator,
        salient_fraction: float | None = None,
        include_input: bool = False,
        pixel_jitter: float = 0.0,
        stride: int = 1,
    ) -> RayBatch:
        """Build the batch for the given scene positions (CPU tensors).

        ``salient_fraction`` overrides the share of rays a salient strategy
        (:data:`~svorf.ray_sampling.SALIENT_RAY_SAMPLING`) draws from salient pixels
        (0 = uniform); None keeps the strategy's own. ``include_input`` (novel-view setup
        only) makes the input view one of the target views (``TrainConfig.input_view_from``).
        ``pixel_jitter`` > 0 moves each ray off its pixel centre by a uniform draw from a
        square of that side (pixels; ``TrainConfig.pixel_jitter``), the target still the
        pixel's colour; the offsets are drawn after the pixels, which stay those drawn
        without it, and 0 draws nothing (the batches of earlier versions). ``stride`` > 1
        (``TrainConfig.coarse_to_fine``) draws the rays on the views area-averaged by that
        factor: each ray through the centre of its ``stride`` x ``stride`` block, its target
        the block's mean colour, ``target_pixel`` the block's top-left pixel.
        """
        draw = self._fn
        if salient_fraction is not None:
            if self.ray_sampling not in SALIENT_RAY_SAMPLING:
                raise ValueError(
                    f"salient_fraction needs a salient strategy {sorted(SALIENT_RAY_SAMPLING)}, "
                    f"this sampler's is {self.ray_sampling!r}"
                )
            draw = partial(self._fn, fraction=float(salient_fraction))
        ds = self.dataset
        scenes = torch.as_tensor(scenes, dtype=torch.long).reshape(-1)
        v_all, (h, w) = ds.n_views, ds.image_hw
        r = self.rays_per_scene
        if stride > 1 and (h % stride or w % stride or self.error_map is not None or pixel_jitter):
            raise ValueError(
                f"stride {stride} needs views whose sides are multiples of it (these are "
                f"{h}x{w}), no error map and no pixel_jitter"
            )
        inputs = torch.randint(0, v_all, (len(scenes),), generator=generator)
        out = {
            k: []
            for k in (
                "images",
                "rays_o",
                "rays_d",
                "target_rgb",
                "target_view",
                "target_pixel",
                "input_c2w",
            )
        }
        for s, iv in zip(scenes.tolist(), inputs.tolist()):
            if self.nvs:
                views = torch.tensor([v for v in range(v_all) if v != iv or include_input])
            else:
                views = torch.tensor([iv])
            out["images"].append(ds.images(s, [iv])[0])
            if stride > 1:
                rays_o, rays_d, vsel, pix, rgb = self._blocks(s, views, draw, stride, generator)
            else:
                if self.error_map is not None:
                    flat = self.error_map.draw(s, views, r, generator)
                else:
                    flat = draw(ds._rgb[s][views], r, generator)
                vsel = views[flat // (h * w)]
                pix = flat % (h * w)
                rays_o, rays_d = ds.rays(s, vsel, pix)
                rgb = ds._rgb[s].reshape(v_all, h * w, 3)[vsel, pix].float() / 255.0
            out["rays_o"].append(rays_o)
            out["rays_d"].append(rays_d)
            out["target_rgb"].append(rgb)
            out["target_view"].append(vsel)
            out["target_pixel"].append(pix)
            out["input_c2w"].append(ds._c2w[s][iv].float())
        batch = {k: torch.stack(x) for k, x in out.items()}
        if pixel_jitter > 0:  # drawn after every pixel, so the pixels are those without it
            offset = torch.rand(len(scenes), r, 2, generator=generator, dtype=torch.float64)
            offset = (offset - 0.5) * pixel_jitter
            batch["rays_d"] = torch.stack(
                [
                    ds.rays(s, batch["target_view"][i], batch["target_pixel"][i], offset[i])[1]
                    for i, s in enumerate(scenes.tolist())
                ]
            )
        if self.input_size is not None and (self.input_size,) * 2 != (h, w):
            size = (self.input_size, self.input_size)
            batch["images"] = F.interpolate(batch["images"], size=size, mode="area")
        return RayBatch(scenes=scenes, input_view=inputs, **batch)

    def _blocks(
        self, s: int, views: Tensor, draw: RaySamplingFn, stride: int, generator: torch.Generator
    ) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
        """Rays of scene position ``s`` at ``1/stride`` the resolution (:meth:`sample`):
        ``(rays_o, rays_d, view, top-left pixel, target colour)``, one row per ray."""
        ds = self.dataset
        (h, w), k = ds.image_hw, stride
        hc, wc = h // k, w // k
        x = ds._rgb[s][views].permute(0, 3, 1, 2).float()  # [Vt, 3, H, W], 0-255
        mean = F.avg_pool2d(x, k).permute(0, 2, 3, 1)  # [Vt, hc, wc, 3]
        flat = draw(mean.round().to(torch.uint8), self.rays_per_scene, generator)
        vi, cell = flat // (hc * wc), flat % (hc * wc)
        pix = (cell // wc) * k * w + (cell % wc) * k
        centre = torch.full((len(flat), 2), (k - 1) / 2.0, dtype=torch.float64)
        rays_o, rays_d = ds.rays(s, views[vi], pix, centre)
        return rays_o, rays_d, views[vi], pix, mean.reshape(-1, 3)[flat] / 255.0


def gray_some_scenes(batch: RayBatch, p: float, gen: torch.Generator) -> RayBatch:
    """``batch`` with each scene, by chance ``p`` (``TrainConfig.gray_scenes``), shown in
    Rec.601 luma: its input view and its target rays, all three channels equal."""
    pick = torch.rand(batch.scenes.shape[0], generator=gen) < p
    if not bool(pick.any()):
        return batch
    w = torch.tensor(LUMA_REC601, dtype=batch.images.dtype)
    images, target = batch.images.clone(), batch.target_rgb.clone()
    images[pick] = torch.einsum("bchw,c->bhw", images[pick], w)[:, None].expand(-1, 3, -1, -1)
    target[pick] = (target[pick] @ w)[..., None].expand(-1, -1, 3)
    return replace(batch, images=images, target_rgb=target)
