"""Embree ray casting of a SceneSpec: instance ids and planar depth without Blender.

Data flow: ``sampling`` calls :func:`cast_view` on view 0 to check that every
object is visible before a scene is accepted (so the check costs ~15 ms instead of
a render); tests use it as an independent oracle for the rendered index/Z passes.
Rays go through pixel centres, exactly like the first Cycles sample, which is the
one that writes Cycles' (non-anti-aliased) index and Z passes.

Needs ``trimesh`` with ``embreex`` (pure-numpy trimesh ray casting is far too slow).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from generators import geometry
from generators.spec import SceneSpec


@dataclass(frozen=True)
class CastResult:
    """Ray-cast passes of one view.

    Attributes:
        ids: uint8 [H, W] instance ids (0 = background: ground or nothing).
        depth_z: float32 [H, W] planar depth (camera z, world units); inf where
            the ray hits nothing.
    """

    ids: np.ndarray
    depth_z: np.ndarray


def intersector(mesh: geometry.TriMesh) -> Any:
    """An embree ray intersector of ``mesh`` (``trimesh.ray.ray_pyembree.RayMeshIntersector``:
    ``intersects_first``, ``intersects_location``); build it once, query it many times.

    Raises:
        ImportError: trimesh with embree is not installed (the message names the fix).
    """
    try:
        import trimesh
        from trimesh.ray.ray_pyembree import RayMeshIntersector
    except ImportError as e:  # pragma: no cover - install problem
        raise ImportError(
            "the visibility check needs trimesh with embree: pip install trimesh embreex"
        ) from e
    tm = trimesh.Trimesh(mesh.vertices, mesh.faces, process=False, validate=False)
    return RayMeshIntersector(tm)


def cast_view(spec: SceneSpec, view: int, resolution: int | None = None, meshes=None) -> CastResult:
    """Ray-cast view ``view`` of ``spec`` through every pixel centre.

    Args:
        spec: the scene.
        view: view index.
        resolution: square image size (default: ``spec.render.resolution``).
        meshes: optional precomputed ``spec.meshes()`` (saves time when casting
            several views of one scene).

    Returns:
        :class:`CastResult` with ``[resolution, resolution]`` arrays.
    """
    if not 0 <= view < spec.n_views:
        raise ValueError(f"view must be in [0, {spec.n_views}), got {view}")
    res = spec.render.resolution if resolution is None else int(resolution)
    if res < 1:
        raise ValueError(f"resolution must be >= 1, got {res}")
    mesh_list, ids = meshes if meshes is not None else spec.meshes()
    merged, owner = geometry.concat_meshes(mesh_list)
    face_ids = np.asarray(ids, dtype=np.uint8)[owner]
    v = spec.views[view]
    K, c2w = v.K(res, res), v.c2w()
    origins, dirs = geometry.pixel_rays(K, c2w, res, res)
    inter = intersector(merged)
    locs, ray_idx, tri_idx = inter.intersects_location(origins, dirs, multiple_hits=False)
    out_ids = np.zeros(res * res, dtype=np.uint8)
    depth = np.full(res * res, np.inf, dtype=np.float64)
    if len(ray_idx):
        out_ids[ray_idx] = face_ids[tri_idx]
        # dirs have camera-z 1, so planar depth = distance along the optical axis.
        fwd = c2w[:3, 2]
        depth[ray_idx] = (locs - origins[ray_idx]) @ fwd
    return CastResult(out_ids.reshape(res, res), depth.astype(np.float32).reshape(res, res))
