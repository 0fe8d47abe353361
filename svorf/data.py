"""Multi-view scene dataset with cached rays, and the training ray sampler.

Where this sits: ``dataset on disk -> svorf.data -> model``. :class:`MultiViewDataset`
reads a generated split folder (the :mod:`scenefmt` contract) once into memory,
optionally resized to the training resolution, and caches one ray per pixel per
view. :class:`RaySampler` draws the training batches of the paper's setup (one input
view per scene, ``R`` random rays from the scene's other views), the pixels picked by a
strategy of :data:`RAY_SAMPLING` (``"uniform"`` = paper; ``"object_heavy"`` = label-free,
half the rays from pixels far from the image's median colour; ``"error_driven"`` =
label-free, half the rays from image tiles in proportion to the model's recent error
there, kept by an :class:`ErrorMap`).

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

import hashlib
import math
import os
import re
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from PIL import Image
from torch import Tensor

from scenefmt import (
    SplitLayout,
    read_depth_exr,
    read_instances,
    read_json,
    read_matrix_txt,
    read_rgb,
    sentinel_size,
)

__all__ = [
    "RAY_SAMPLING",
    "STATEFUL_RAY_SAMPLING",
    "UORF_FOV_DEG",
    "DatasetError",
    "ErrorMap",
    "MultiViewDataset",
    "RayBatch",
    "RaySampler",
    "SceneViews",
    "contrast_pixels",
    "dataset_fingerprint",
    "object_contrast_rays",
    "object_heavy_rays",
    "pixel_rays",
    "rays_at",
    "register_ray_sampling",
    "resize_intrinsics",
    "salient_pixels",
]

#: Field of view (x, y) in degrees assumed for uORF-layout folders, which store no
#: intrinsics: uORF's ``models/projection.py`` uses focal lengths of ``350/320 * W`` and
#: ``350/240 * H`` pixels, i.e. ``2 * atan(0.5 / ratio)``.
UORF_FOV_DEG = (
    math.degrees(2.0 * math.atan(0.5 / (350.0 / 320.0))),
    math.degrees(2.0 * math.atan(0.5 / (350.0 / 240.0))),
)

#: File-name endings the uORF loader excludes from its view-image glob, plus the
#: auxiliary images seen in uORF-derived repositories (``_dist``, ``_depth``, ``_seg``).
UORF_EXCLUDED_SUFFIXES = (
    "_mask",
    "_mask_for_moving",
    "_moved",
    "_mask_for_bg",
    "_mask_for_providing_bg",
    "_changed",
    "_providing_bg",
    "_dist",
    "_depth",
    "_seg",
)

# OpenGL camera axes (x right, y up, z backward) -> OpenCV: negate the y and z columns.
_GL_TO_CV = np.diag([1.0, -1.0, -1.0, 1.0])


class DatasetError(ValueError):
    """A split folder that cannot be read; the message is one line naming the fix."""


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


def _rays_from_kinv(kinv: Tensor, cam_to_world: Tensor, u: Tensor, v: Tensor):
    """:func:`rays_at` with ``K^-1`` (float64) given: the dataset inverts each K once."""
    rot = cam_to_world.double()[..., :3, :3]
    uc, vc = u.double() + 0.5, v.double() + 0.5
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


def dataset_fingerprint(root: str | os.PathLike) -> str:
    """SHA-256 over ``manifest.json`` and every ``sc*.json`` of a split (hex string).

    The scene JSONs record every random draw and camera, so two folders with the same
    fingerprint hold the same scenes (render noise aside). For uORF-layout folders
    (no JSON) the hash runs over the sorted view-image names and ``_RT.txt`` contents.
    """
    root = Path(root)
    h = hashlib.sha256()
    files = [root / "manifest.json"] if (root / "manifest.json").is_file() else []
    files += sorted(root.glob("sc[0-9][0-9][0-9][0-9].json"))
    if not files:
        files = sorted(root.glob("*_RT.txt"))
    for p in files:
        h.update(p.name.encode() + b"\0")
        h.update(p.read_bytes() + b"\0")
    return h.hexdigest()


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
            second-lowest-grey-level background rule (see :func:`_uorf_ids`), all
            background when the mask is absent. The folder fingerprint hashes the
            ``_RT.txt`` files.
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
        self.manifest: dict = {}
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

    def _read(self, reader: Callable, path: Path):
        """``reader(path)`` with any decoding failure turned into a one-line DatasetError."""
        try:
            return reader(path)
        except FileNotFoundError as e:
            raise self._missing(path) from e
        except (OSError, ValueError, SyntaxError) as e:
            msg = (str(e).strip().splitlines() or [type(e).__name__])[0]
            raise DatasetError(
                f"{path}: unreadable ({msg[:120]}); run `generate verify {self.root}` "
                f"and regenerate the scene"
            ) from e

    def _missing(self, path: Path) -> DatasetError:
        return DatasetError(
            f"{path}: missing - {self.root} is not a complete split folder "
            f"(run `generate verify {self.root}`)"
        )

    def _load_ours(self, max_scenes: int | None):
        manifest_path = self.root / "manifest.json"
        if not manifest_path.is_file():
            raise self._missing(manifest_path)
        try:
            self.manifest = read_json(manifest_path)
        except (OSError, ValueError) as e:
            raise DatasetError(
                f"{manifest_path}: unreadable JSON ({e}); run `generate verify {self.root}`"
            ) from e
        n_views = int(self.manifest.get("n_views", 4))
        layout = SplitLayout(self.root, n_views=n_views)
        scenes = layout.scene_indices()
        if not scenes:
            raise DatasetError(
                f"{self.root}: no sc%04d.json scene files - not a generated split folder "
                f"(run `generate verify {self.root}`)"
            )
        if "n_scenes" in self.manifest and len(scenes) < int(self.manifest["n_scenes"]):
            expected = set(range(int(self.manifest["n_scenes"])))
            first = min(expected - set(scenes), default=None)
            if first is not None:
                raise self._missing(layout.scene_json(first))
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
                    raise self._missing(p)
            jpath = layout.scene_json(s)
            meta = self._read(read_json, jpath)
            if not isinstance(meta, dict):
                raise DatasetError(f"{jpath}: not a scene record (a JSON object expected)")
            conv = meta.get("camera_convention", "opencv")
            if conv != "opencv":
                raise DatasetError(f"{jpath}: camera_convention {conv!r} is not 'opencv'")
            dconv = meta.get("depth", "planar_z")
            if dconv != "planar_z":
                raise DatasetError(f"{jpath}: depth convention {dconv!r} is not 'planar_z'")
            views = meta.get("views")
            if not isinstance(views, list) or len(views) != n_views:
                got = len(views) if isinstance(views, list) else "no"
                raise DatasetError(f"{jpath}: expected {n_views} entries in 'views', got {got}")
            s_rgb, s_ids, s_depth, s_K, s_c2w = [], [], [], [], []
            for view, vm in enumerate(views):
                try:
                    Kv = np.asarray(vm["K"], dtype=np.float64)
                    Tv = np.asarray(vm["cam_to_world"], dtype=np.float64)
                except (KeyError, TypeError, ValueError) as e:
                    raise DatasetError(
                        f"{jpath}: view {view} lacks a valid K / cam_to_world ({e})"
                    ) from e
                if Kv.shape != (3, 3) or Tv.shape != (4, 4):
                    raise DatasetError(
                        f"{jpath}: view {view} K must be 3x3 and cam_to_world 4x4, "
                        f"got {Kv.shape} and {Tv.shape}"
                    )
                if "image" in vm and Path(vm["image"]).name != layout.rgb(s, view).name:
                    raise DatasetError(
                        f"{jpath}: view {view} image {vm['image']!r} does not match the "
                        f"layout name {layout.rgb(s, view).name!r}"
                    )
                img = self._read(read_rgb, layout.rgb(s, view))
                s_rgb.append(img)
                if self.truth:
                    inst = self._read(read_instances, layout.instances(s, view))
                    dz = self._read(read_depth_exr, layout.depth(s, view))
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
        pngs = sorted(self.root.glob("*.png"))
        views = [p for p in pngs if not p.stem.endswith(UORF_EXCLUDED_SUFFIXES)]
        by_scene: dict[int, list[Path]] = {}
        for p in views:
            m = re.search(r"sc(\d{4})", p.name)
            if m:
                by_scene.setdefault(int(m.group(1)), []).append(p)
        if not by_scene:
            raise DatasetError(
                f"{self.root}: no view images named *sc%04d*.png - not a uORF-layout folder"
            )
        scenes = self._select(sorted(by_scene), max_scenes)
        counts = {len(by_scene[s]) for s in scenes}
        if len(counts) != 1:
            raise DatasetError(f"{self.root}: scenes have different view counts {sorted(counts)}")
        fx_deg, fy_deg = (fov_deg, fov_deg) if isinstance(fov_deg, (int, float)) else fov_deg
        rgb, ids, depth, Ks, c2ws = [], [], [], [], []
        for s in scenes:
            files = sorted(by_scene[s])
            s_rgb = [self._read(read_rgb, p) for p in files]
            if len({a.shape for a in s_rgb}) != 1:
                raise DatasetError(f"{self.root}: the views of scene sc{s:04d} differ in size")
            h, w = s_rgb[0].shape[:2]
            fx = 0.5 * w / math.tan(math.radians(fx_deg) / 2.0)
            fy = 0.5 * h / math.tan(math.radians(fy_deg) / 2.0)
            Kv = np.array([[fx, 0.0, w / 2.0], [0.0, fy, h / 2.0], [0.0, 0.0, 1.0]])
            s_c2w, s_depth, s_levels = [], [], []
            for p in files:
                rt = p.with_name(p.stem + "_RT.txt")
                if not rt.is_file():
                    raise DatasetError(f"{rt}: missing - every uORF view image needs its _RT.txt")
                T = self._read(read_matrix_txt, rt)
                if T.shape != (4, 4):
                    raise DatasetError(f"{rt}: expected a 4x4 matrix, got shape {T.shape}")
                s_c2w.append(T @ _GL_TO_CV if axes == "opengl" else T)
                if not self.truth:
                    continue
                dpath = p.with_name(p.stem + "_depth.npy")
                if dpath.is_file():  # assumed planar z (what our writer stores there)
                    dz = self._read(np.load, dpath)
                    if dz.size != h * w:
                        raise DatasetError(f"{dpath}: {dz.shape} does not match the {h}x{w} image")
                    s_depth.append(dz.reshape(h, w).astype(np.float32))
                else:
                    s_depth.append(np.full((h, w), np.nan, dtype=np.float32))
                mpath = p.with_name(p.stem + "_mask.png")
                if mpath.is_file():
                    s_levels.append(self._read(_read_grey, mpath))
                else:
                    s_levels.append(None)
            rgb.append(np.stack(s_rgb))
            if self.truth:
                ids.append(_uorf_ids(s_levels, h, w))
                depth.append(np.stack(s_depth))
            Ks.append(np.stack([Kv] * len(files)))
            c2ws.append(np.stack(s_c2w))
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

    def rays(self, i: int, views: Tensor, pixels: Tensor) -> tuple[Tensor, Tensor]:
        """``(rays_o [R, 3], rays_d [R, 3])`` of scene position ``i`` through flat pixel
        indices ``pixels`` [R] (``row * W + column``) of ``views`` [R]: the same values as
        ``self[i].rays_d[views, row, column]``, computed for these pixels only."""
        w = self.image_hw[1]
        kinv, c2w = self._Kinv64[i][views], self._c2w64[i][views]
        rays_d, _ = _rays_from_kinv(kinv, c2w, pixels % w, pixels // w)
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
        return self.manifest.get("preset")


def _read_grey(path: Path) -> np.ndarray:
    with Image.open(path) as im:
        return np.asarray(im.convert("L"))


def _uorf_ids(levels: list[np.ndarray | None], h: int, w: int) -> np.ndarray:
    """Instance ids [V, H, W] from uORF grey masks with the uORF background rule.

    Per view the background is the *second-lowest* grey level (uORF's loader); every
    other level is an object, with one exception: when the lowest level holds pixel
    (0, 0) and occupies only pixels of the top-left ``b x b`` block
    (``b = scenefmt.sentinel_size(h, w)`` of that view's mask) it is our writer's
    sentinel (``scenefmt.MASK_SENTINEL_LEVEL``, there so that the second-lowest rule
    holds) and reads as background. That covers the whole block (format >= 1.1) and
    the single pixel (0, 0) of format 1.0 files. uORF's own loader would see it as a
    small object. Ids 1..n follow the sorted union of object levels over the scene's
    views, so one object keeps its id across views (assumes a grey level means the
    same object in every view of a scene, as in uORF's data). Views without a mask
    read as all background.

    Args:
        levels: per view a uint8 [h, w] grey mask (after ``convert('L')``) or None.
        h, w: the views' image size (each mask is [h, w]).
    """
    out = np.zeros((len(levels), h, w), dtype=np.uint8)
    bgs: list[set[int] | None] = []
    fg_levels: set[int] = set()
    for m in levels:
        if m is None:
            bgs.append(None)
            continue
        uniq = np.unique(m)
        bg = {int(uniq[1] if len(uniq) > 1 else uniq[0])}
        corner = int(m[0, 0])
        if len(uniq) > 1 and corner == int(uniq[0]):
            b = sentinel_size(*m.shape)
            low = m == corner
            if int(low.sum()) == int(low[:b, :b].sum()):
                bg.add(corner)  # the sentinel block (or format 1.0's pixel (0, 0))
        bgs.append(bg)
        fg_levels.update(int(u) for u in uniq if int(u) not in bg)
    lut = {lv: k + 1 for k, lv in enumerate(sorted(fg_levels))}
    if len(lut) > 255:
        raise DatasetError("uORF masks have more than 255 object grey levels")
    for j, (m, bg) in enumerate(zip(levels, bgs)):
        if m is None or bg is None:
            continue
        table = np.zeros(256, dtype=np.uint8)
        for lv, k in lut.items():
            table[lv] = k
        for lv in bg:
            table[lv] = 0
        out[j] = table[m]
    return out


# --------------------------------------------------------------------------- ray sampling

#: A ray-sampling strategy: ``fn(target_rgb, n, generator) -> flat indices``.
#: ``target_rgb`` is uint8 [Vt, H, W, 3] (the scene's candidate target views); the
#: result is int64 [n] indices into ``Vt * H * W``. Strategies must draw all their
#: randomness from ``generator`` (determinism and exact resume).
RaySamplingFn = Callable[[Tensor, int, torch.Generator], Tensor]


def _uniform_rays(target_rgb: Tensor, n: int, generator: torch.Generator) -> Tensor:
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
) -> Tensor:
    """Label-free object-heavy sampling (no ground-truth masks).

    ``round(fraction * n)`` rays come uniformly (with replacement) from the salient
    pixels of :func:`salient_pixels` over all target views; the rest, or all ``n`` when
    no pixel is salient, come uniformly from every pixel. On CLEVR-like 64x64 data
    objects cover ~6% of the pixels but ~77% of the salient ones, so objects get a
    gradient from the first steps instead of a "mean scene" plateau.
    """
    if not 0.0 <= fraction <= 1.0:
        raise ValueError(f"object_heavy fraction must be in [0, 1], got {fraction}")
    total = target_rgb.shape[0] * target_rgb.shape[1] * target_rgb.shape[2]
    cand = salient_pixels(target_rgb, threshold).reshape(-1).nonzero().squeeze(1)
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
        return {"err": self.err.clone(), "tile": self.tile}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        err = state["err"]
        if tuple(err.shape) != tuple(self.err.shape) or int(state["tile"]) != self.tile:
            raise ValueError(
                f"ErrorMap: saved map {tuple(err.shape)} (tile {state['tile']}) does not fit "
                f"this dataset {tuple(self.err.shape)} (tile {self.tile})"
            )
        self.err.copy_(err)


#: Registry of ray-sampling strategies by name (``TrainConfig.ray_sampling``).
#: ``"error_driven"`` is stateful: :class:`RaySampler` draws it from its :class:`ErrorMap`
#: (the trainer feeds the map); called as a plain function it is uniform sampling.
RAY_SAMPLING: dict[str, RaySamplingFn] = {
    "uniform": _uniform_rays,
    "object_heavy": object_heavy_rays,
    "object_contrast": object_contrast_rays,
    "error_driven": _uniform_rays,
}
#: Strategies that need an :class:`ErrorMap` fed with each step's per-ray errors.
STATEFUL_RAY_SAMPLING = frozenset({"error_driven"})


def register_ray_sampling(name: str, fn: RaySamplingFn) -> None:
    """Add a strategy to :data:`RAY_SAMPLING` (e.g. object-heavy or error-driven)."""
    if name in RAY_SAMPLING:
        raise ValueError(f"ray sampling strategy {name!r} is already registered")
    RAY_SAMPLING[name] = fn


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
    """

    def __init__(
        self,
        dataset: MultiViewDataset,
        rays_per_scene: int = 64,
        *,
        nvs: bool = True,
        ray_sampling: str = "uniform",
        error_map: ErrorMap | None = None,
    ) -> None:
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

    def sample(self, scenes: Tensor | Sequence[int], generator: torch.Generator) -> RayBatch:
        """Build the batch for the given scene positions (CPU tensors)."""
        ds = self.dataset
        scenes = torch.as_tensor(scenes, dtype=torch.long).reshape(-1)
        v_all, (h, w) = ds.n_views, ds.image_hw
        r = self.rays_per_scene
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
                views = torch.tensor([v for v in range(v_all) if v != iv])
            else:
                views = torch.tensor([iv])
            if self.error_map is not None:
                flat = self.error_map.draw(s, views, r, generator)
            else:
                flat = self._fn(ds._rgb[s][views], r, generator)
            vsel = views[flat // (h * w)]
            pix = flat % (h * w)
            out["images"].append(ds.images(s, [iv])[0])
            rays_o, rays_d = ds.rays(s, vsel, pix)
            out["rays_o"].append(rays_o)
            out["rays_d"].append(rays_d)
            out["target_rgb"].append(ds._rgb[s].reshape(v_all, h * w, 3)[vsel, pix].float() / 255.0)
            out["target_view"].append(vsel)
            out["target_pixel"].append(pix)
            out["input_c2w"].append(ds._c2w[s][iv].float())
        return RayBatch(
            scenes=scenes, input_view=inputs, **{k: torch.stack(x) for k, x in out.items()}
        )
