"""A tiny numpy-only synthetic split writer: the test fixture of ``svorf`` and ``benchmark``.

Where this sits: it stands in for ``generate`` (Blender) in tests. It writes a small
but *valid* split in the on-disk contract of :mod:`scenefmt` (RGB, ``_RT.txt``,
``_azi_rot.txt``, uORF ``_mask.png``, lossless instance ids, planar-depth EXR, scene
JSON, manifest) for scenes of a few coloured spheres resting on a square ground
plate, ray cast analytically, so depth and instance ids are exact:

- cameras on the standard rig: radius 12.4, elevation 40 degrees, random azimuths,
  looking at the origin, OpenCV axes (x right, y down, z forward), z-up world;
- intrinsics ``K = [[f, 0, W/2], [0, f, H/2], [0, 0, 1]]`` with pixel centres at
  ``(u + 0.5, v + 0.5)`` and ``f = 50 / 36 * W`` (Blender's default 50 mm lens on a
  36 mm sensor, a horizontal field of view of 39.6 degrees);
- depth is planar (camera z) in world units; rays that miss everything (beyond the
  plate) read ``inf`` and instance id 0;
- shading is Lambert with one directional light plus ambient, no shadows; the
  stored colours are treated as sRGB directly.

Example:
    >>> from svorf.synthetic import write_synthetic_split
    >>> root = write_synthetic_split("/tmp/synth/train", n_scenes=2, resolution=32)
"""

from __future__ import annotations

import math
import os
from pathlib import Path

import numpy as np

from scenefmt import (
    Manifest,
    SceneRecord,
    SplitLayout,
    ViewRecord,
    atomic_write_json,
    uorf_mask_from_instances,
    write_depth_exr,
    write_instances,
    write_mask,
    write_matrix_txt,
    write_rgb,
)
from scenefmt.clevr import CLEVR_COLORS, CLEVR_SIZES

__all__ = ["RIG_ELEVATION_DEG", "RIG_RADIUS", "look_at_opencv", "write_synthetic_split"]

#: Standard camera rig.
RIG_RADIUS = 12.4
RIG_ELEVATION_DEG = 40.0
#: Focal length as a fraction of the image width (50 mm lens, 36 mm sensor).
FOCAL_RATIO = 50.0 / 36.0
#: Half side of the square ground plate (world units); beyond it rays miss.
PLATE_HALF = 6.0

_COLOURS = CLEVR_COLORS
_SIZES = CLEVR_SIZES
_PLATE_RGB = np.array([0.62, 0.62, 0.60])
_SKY_RGB = np.array([0.08, 0.08, 0.10])
_LIGHT_DIR = np.array([0.4, -0.3, 0.866]) / np.linalg.norm([0.4, -0.3, 0.866])
_AMBIENT = 0.35


def look_at_opencv(eye: np.ndarray, target: np.ndarray | None = None) -> np.ndarray:
    """Camera-to-world 4x4 (OpenCV axes) for a camera at ``eye`` looking at ``target``.

    World is z-up; the camera's x axis is horizontal (no roll).
    """
    eye = np.asarray(eye, dtype=np.float64)
    target = np.zeros(3) if target is None else np.asarray(target, dtype=np.float64)
    forward = target - eye
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    c2w = np.eye(4)
    c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3] = right, down, forward, eye
    return c2w


def _azimuth_rotation(azimuth: float) -> np.ndarray:
    c, s = math.cos(azimuth), math.sin(azimuth)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _sample_objects(rng: np.random.Generator, n_objects: int) -> list[dict]:
    objects: list[dict] = []
    names = list(_COLOURS)
    tries = 0
    while len(objects) < n_objects:
        tries += 1
        if tries > 10_000:  # pragma: no cover - the area is far from full
            raise RuntimeError("could not place the synthetic objects")
        size = "large" if rng.random() < 0.5 else "small"
        radius = _SIZES[size]
        xy = rng.uniform(-2.5, 2.5, size=2)
        if any(
            np.linalg.norm(xy - np.asarray(o["position"][:2])) < radius + o["radius"] + 0.25
            for o in objects
        ):
            continue
        colour = names[int(rng.integers(len(names)))]
        objects.append(
            {
                "instance_id": len(objects) + 1,
                "shape": "sphere",
                "color": colour,
                "rgb": list(_COLOURS[colour]),
                "material": "rubber",
                "size": radius,
                "size_name": size,
                "radius": radius,
                "position": [float(xy[0]), float(xy[1]), radius],
                "rotation": 0.0,
            }
        )
    return objects


def _pixel_rays(K: np.ndarray, c2w: np.ndarray, h: int, w: int) -> tuple[np.ndarray, np.ndarray]:
    """World-frame unit ray directions [H, W, 3] and camera-z of those units [H, W]."""
    u, v = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)
    pix = np.stack([u, v, np.ones_like(u)], axis=-1)
    d_cam = pix @ np.linalg.inv(K).T
    d_cam /= np.linalg.norm(d_cam, axis=-1, keepdims=True)
    return d_cam @ c2w[:3, :3].T, d_cam[..., 2]


def _render_view(
    objects: list[dict], K: np.ndarray, c2w: np.ndarray, h: int, w: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Analytic ray cast: (rgb uint8 [H,W,3], ids uint8 [H,W], depth_z float32 [H,W])."""
    dirs, z_scale = _pixel_rays(K, c2w, h, w)
    origin = c2w[:3, 3]
    t_best = np.full((h, w), np.inf)
    ids = np.zeros((h, w), dtype=np.uint8)
    normal = np.zeros((h, w, 3))
    albedo = np.broadcast_to(_SKY_RGB, (h, w, 3)).copy()
    hit_any = np.zeros((h, w), dtype=bool)

    # Ground plate z = 0 (|x|, |y| <= PLATE_HALF).
    with np.errstate(divide="ignore", invalid="ignore"):
        t_plane = -origin[2] / dirs[..., 2]
    p = origin + t_plane[..., None] * dirs
    on_plate = (t_plane > 0) & (np.abs(p[..., 0]) <= PLATE_HALF) & (np.abs(p[..., 1]) <= PLATE_HALF)
    t_best[on_plate] = t_plane[on_plate]
    normal[on_plate] = (0.0, 0.0, 1.0)
    albedo[on_plate] = _PLATE_RGB
    hit_any |= on_plate

    for obj in objects:
        centre = np.asarray(obj["position"], dtype=np.float64)
        oc = origin - centre
        b = dirs @ oc
        c = oc @ oc - obj["radius"] ** 2
        disc = b * b - c
        with np.errstate(invalid="ignore"):
            t = -b - np.sqrt(disc)
        hit = (disc > 0) & (t > 0) & (t < t_best)
        t_best[hit] = t[hit]
        ids[hit] = obj["instance_id"]
        n = origin + t[..., None] * dirs - centre
        normal[hit] = n[hit] / obj["radius"]
        albedo[hit] = np.asarray(obj["rgb"]) / 255.0
        hit_any |= hit

    shade = _AMBIENT + (1.0 - _AMBIENT) * np.clip(normal @ _LIGHT_DIR, 0.0, None)
    rgb = np.where(hit_any[..., None], albedo * shade[..., None], _SKY_RGB)
    rgb8 = np.clip(np.round(rgb * 255.0), 0, 255).astype(np.uint8)
    depth_z = np.where(hit_any, t_best * z_scale, np.inf).astype(np.float32)
    return rgb8, ids, depth_z


def write_synthetic_split(
    root: str | os.PathLike,
    n_scenes: int = 2,
    resolution: int = 32,
    seed: int = 0,
    *,
    n_views: int = 4,
    n_objects: tuple[int, int] = (2, 3),
    preset: str = "synthetic",
    split: str = "train",
) -> Path:
    """Write a tiny valid split folder of analytic sphere scenes.

    Every scene is a pure function of ``(seed, scene index)``.

    Args:
        root: the split folder to create (parents are created).
        n_scenes: number of scenes (``sc0000`` ... ).
        resolution: square image side H = W in pixels.
        seed: base seed; scene ``i`` uses ``numpy.random.default_rng([seed, i])``.
        n_views: views per scene (random azimuths on the standard rig).
        n_objects: inclusive range of spheres per scene.
        preset: preset name written to the manifest and scene JSONs.
        split: split name written to the manifest and scene JSONs.

    Returns:
        The split folder as a :class:`~pathlib.Path`.
    """
    if n_scenes < 1 or resolution < 4 or n_views < 1:
        raise ValueError(
            f"need n_scenes >= 1, resolution >= 4, n_views >= 1; "
            f"got {n_scenes}, {resolution}, {n_views}"
        )
    layout = SplitLayout(Path(root), n_views=n_views)
    layout.root.mkdir(parents=True, exist_ok=True)
    h = w = int(resolution)
    f = FOCAL_RATIO * w
    K = np.array([[f, 0.0, w / 2.0], [0.0, f, h / 2.0], [0.0, 0.0, 1.0]])
    elevation = math.radians(RIG_ELEVATION_DEG)

    for scene in range(n_scenes):
        rng = np.random.default_rng([seed, scene])
        objects = _sample_objects(rng, int(rng.integers(n_objects[0], n_objects[1] + 1)))
        views = []
        for view in range(n_views):
            azimuth = float(rng.uniform(0.0, 2.0 * math.pi))
            eye = RIG_RADIUS * np.array(
                [
                    math.cos(elevation) * math.cos(azimuth),
                    math.cos(elevation) * math.sin(azimuth),
                    math.sin(elevation),
                ]
            )
            c2w = look_at_opencv(eye)
            rgb, ids, depth_z = _render_view(objects, K, c2w, h, w)
            write_rgb(layout.rgb(scene, view), rgb)
            write_matrix_txt(layout.rt(scene, view), c2w)
            write_matrix_txt(layout.azi_rot(scene, view), _azimuth_rotation(azimuth))
            write_mask(layout.mask(scene, view), uorf_mask_from_instances(ids))
            write_instances(layout.instances(scene, view), ids)
            write_depth_exr(layout.depth(scene, view), depth_z)
            views.append(
                ViewRecord(
                    image=layout.rgb(scene, view).name,
                    K=K.tolist(),
                    cam_to_world=c2w.tolist(),
                    extra={
                        "view": view,
                        "azimuth_deg": math.degrees(azimuth),
                        "elevation_deg": RIG_ELEVATION_DEG,
                        "radius": RIG_RADIUS,
                        "look_at": [0.0, 0.0, 0.0],
                        "lens_mm": 50.0,
                        "sensor_width_mm": 36.0,
                        "sensor_fit": "HORIZONTAL",
                    },
                )
            )
        record = SceneRecord(
            preset=preset,
            split=split,
            index=scene,
            seed=seed,
            views=tuple(views),
            objects=tuple(objects),
            extra={
                "lights": [{"type": "directional", "direction": _LIGHT_DIR.tolist()}],
                "render": {"engine": "svorf.synthetic (analytic ray cast)", "resolution": h},
            },
        )
        atomic_write_json(layout.scene_json(scene), record.to_json())
    manifest = Manifest(
        preset=preset,
        split=split,
        n_scenes=n_scenes,
        n_views=n_views,
        resolution=h,
        seed=seed,
        generator="svorf.synthetic",
        conventions={
            "camera": "opencv: x right, y down, z forward; z-up world; cam_to_world",
            "intrinsics": "pixel units, pixel centres at (u + 0.5, v + 0.5)",
            "depth": "planar_z: camera z in world units, inf = no surface",
            "instances": "0 = background, k = objects[k-1] of the scene JSON",
        },
    )
    atomic_write_json(layout.manifest, manifest.to_json())
    return layout.root
