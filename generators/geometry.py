"""Camera math and the exact triangle meshes of every primitive (pure numpy).

Data flow: ``sampling`` places objects and cameras with these helpers; the same
vertex/face arrays are handed to ``raycast`` (embree visibility check, tests) and
to ``blender_backend`` (the render). Because both see identical triangles, the
index pass of the render and the analytic ray cast agree pixel for pixel (up to
float32 round-off at silhouettes), which is what makes the sampler's visibility
check trustworthy.

Conventions (see ``docs/format.md``):

* World: right-handed, z up, metres ("world units"), origin = scene centre.
* Camera-to-world matrices use OpenCV axes: x right, y down, z forward. Blender's
  camera ``matrix_world`` is ``cam_to_world @ diag(1, -1, -1, 1)`` (its own inverse).
* Pixel ``(u, v)`` (column, row) covers ``[u, u+1) x [v, v+1)``; its centre is at
  ``(u + 0.5, v + 0.5)``; ``K = [[f, 0, W/2], [0, f, H/2], [0, 0, 1]]`` with
  ``f = lens_mm / sensor_width_mm * W`` (Blender sensor fit HORIZONTAL, square pixels).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

#: OpenCV <-> Blender camera axes flip (x kept, y and z negated); its own inverse.
CV_TO_BLENDER = np.diag([1.0, -1.0, -1.0, 1.0])

#: Tessellation of the curved CLEVR primitives (recorded in every scene JSON).
SPHERE_SUBDIVISIONS = 4  # icosphere: 2562 vertices, 5120 faces
CYLINDER_SEGMENTS = 64


# --------------------------------------------------------------------------- cameras


def camera_position(radius: float, azimuth_deg: float, elevation_deg: float) -> np.ndarray:
    """Point on the sphere of ``radius`` around the origin; azimuth from +x towards +y.

    Returns:
        float64 [3], world units.
    """
    az, el = math.radians(azimuth_deg), math.radians(elevation_deg)
    return np.array(
        [
            radius * math.cos(el) * math.cos(az),
            radius * math.cos(el) * math.sin(az),
            radius * math.sin(el),
        ]
    )


def look_at_cam_to_world(
    eye: np.ndarray, target: np.ndarray | None = None, up: np.ndarray | None = None
) -> np.ndarray:
    """OpenCV camera-to-world matrix of a camera at ``eye`` looking at ``target``, no roll.

    Args:
        eye: float [3] camera centre (world).
        target: float [3] look-at point (default origin).
        up: float [3] world up (default +z); must not be parallel to the view direction.

    Returns:
        float64 [4, 4]: columns are the camera x (right), y (down), z (forward) axes
        and the camera centre.
    """
    eye = np.asarray(eye, dtype=np.float64)
    target = np.zeros(3) if target is None else np.asarray(target, dtype=np.float64)
    up = np.array([0.0, 0.0, 1.0]) if up is None else np.asarray(up, dtype=np.float64)
    fwd = target - eye
    n = np.linalg.norm(fwd)
    if n < 1e-9:
        raise ValueError(f"eye {eye} coincides with target {target}")
    fwd /= n
    right = np.cross(fwd, up)
    nr = np.linalg.norm(right)
    if nr < 1e-9:
        raise ValueError(f"up {up} is parallel to the view direction {fwd}")
    right /= nr
    down = np.cross(fwd, right)
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = right, down, fwd, eye
    return m


def azimuth_rotation(azimuth_deg: float) -> np.ndarray:
    """3x3 rotation about world z by ``azimuth_deg`` (uORF's ``_azi_rot.txt``)."""
    a = math.radians(azimuth_deg)
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def intrinsics(lens_mm: float, sensor_width_mm: float, width: int, height: int) -> np.ndarray:
    """3x3 pixel intrinsics K (pixel centres at +0.5, principal point at the image centre)."""
    if width < 1 or height < 1:
        raise ValueError(f"width/height must be >= 1, got {width}x{height}")
    f = lens_mm / sensor_width_mm * width
    return np.array([[f, 0.0, width / 2.0], [0.0, f, height / 2.0], [0.0, 0.0, 1.0]])


def pixel_rays(K: np.ndarray, cam_to_world: np.ndarray, width: int, height: int):
    """Rays through every pixel centre.

    Returns:
        (origins [H*W, 3], dirs [H*W, 3]) float64, row-major pixel order. ``dirs`` are
        scaled so that their camera-z component is 1: the ray parameter t of a hit
        *is* its planar depth.
    """
    u, v = np.meshgrid(np.arange(width) + 0.5, np.arange(height) + 0.5)
    d_cam = np.stack(
        [(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], axis=-1
    ).reshape(-1, 3)
    dirs = d_cam @ cam_to_world[:3, :3].T
    origins = np.broadcast_to(cam_to_world[:3, 3], dirs.shape).copy()
    return origins, dirs


def project(
    K: np.ndarray, cam_to_world: np.ndarray, points: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Project world points to continuous pixel coordinates.

    Args:
        points: float [N, 3] world points.

    Returns:
        (uv [N, 2] continuous pixel coordinates (floor gives the pixel), z [N] planar depth).
    """
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    w2c = np.linalg.inv(cam_to_world)
    pc = pts @ w2c[:3, :3].T + w2c[:3, 3]
    z = pc[:, 2]
    uv = np.stack([K[0, 0] * pc[:, 0] / z + K[0, 2], K[1, 1] * pc[:, 1] / z + K[1, 2]], axis=1)
    return uv, z


# --------------------------------------------------------------------------- meshes


@dataclass(frozen=True)
class TriMesh:
    """A triangle mesh with per-face smooth-shading flags.

    Attributes:
        vertices: float64 [N, 3].
        faces: int64 [F, 3], counter-clockwise seen from outside.
        smooth: bool [F], True where Blender should shade smooth (curved surfaces).
            Smooth and flat parts never share vertices, so vertex normals of the
            smooth part are not bent by the flat caps.
    """

    vertices: np.ndarray
    faces: np.ndarray
    smooth: np.ndarray

    def transformed(self, yaw_deg: float, translation, scale: float = 1.0) -> TriMesh:
        """Scale, rotate about +z by ``yaw_deg``, then translate."""
        a = math.radians(yaw_deg)
        c, s = math.cos(a), math.sin(a)
        rot = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        v = (self.vertices * scale) @ rot.T + np.asarray(translation, dtype=np.float64)
        return TriMesh(v, self.faces, self.smooth)


def concat_meshes(meshes: list[TriMesh]) -> tuple[TriMesh, np.ndarray]:
    """Concatenate meshes; also returns the source index of every face (int64 [F])."""
    verts, faces, smooth, owner = [], [], [], []
    off = 0
    for i, m in enumerate(meshes):
        verts.append(m.vertices)
        faces.append(m.faces + off)
        smooth.append(m.smooth)
        owner.append(np.full(len(m.faces), i, dtype=np.int64))
        off += len(m.vertices)
    return (
        TriMesh(np.concatenate(verts), np.concatenate(faces), np.concatenate(smooth)),
        np.concatenate(owner),
    )


def _icosphere(subdivisions: int) -> tuple[np.ndarray, np.ndarray]:
    t = (1.0 + 5.0**0.5) / 2.0
    v = [
        [-1, t, 0], [1, t, 0], [-1, -t, 0], [1, -t, 0],
        [0, -1, t], [0, 1, t], [0, -1, -t], [0, 1, -t],
        [t, 0, -1], [t, 0, 1], [-t, 0, -1], [-t, 0, 1],
    ]  # fmt: skip
    f = [
        [0, 11, 5], [0, 5, 1], [0, 1, 7], [0, 7, 10], [0, 10, 11],
        [1, 5, 9], [5, 11, 4], [11, 10, 2], [10, 7, 6], [7, 1, 8],
        [3, 9, 4], [3, 4, 2], [3, 2, 6], [3, 6, 8], [3, 8, 9],
        [4, 9, 5], [2, 4, 11], [6, 2, 10], [8, 6, 7], [9, 8, 1],
    ]  # fmt: skip
    verts = [np.array(p, dtype=np.float64) / np.linalg.norm(p) for p in v]
    faces = [tuple(x) for x in f]
    for _ in range(subdivisions):
        cache: dict[tuple[int, int], int] = {}

        def mid(a: int, b: int, cache: dict[tuple[int, int], int] = cache) -> int:
            key = (a, b) if a < b else (b, a)
            if key not in cache:
                p = verts[a] + verts[b]
                verts.append(p / np.linalg.norm(p))
                cache[key] = len(verts) - 1
            return cache[key]

        new = []
        for a, b, c in faces:
            ab, bc, ca = mid(a, b), mid(b, c), mid(c, a)
            new += [(a, ab, ca), (b, bc, ab), (c, ca, bc), (ab, bc, ca)]
        faces = new
    return np.array(verts), np.array(faces, dtype=np.int64)


_UNIT_SPHERE = _icosphere(SPHERE_SUBDIVISIONS)


def sphere_mesh(radius: float) -> TriMesh:
    """Icosphere of circumradius ``radius`` centred at the origin (all faces smooth)."""
    v, f = _UNIT_SPHERE
    return TriMesh(v * radius, f, np.ones(len(f), dtype=bool))


def cube_mesh(edge: float) -> TriMesh:
    """Axis-aligned cube of edge length ``edge`` centred at the origin (flat, 24 vertices)."""
    h = edge / 2.0
    verts, faces = [], []
    for axis in range(3):
        for sign in (-1.0, 1.0):
            u, w = (axis + 1) % 3, (axis + 2) % 3
            quad = []
            for a, b in ((-1, -1), (1, -1), (1, 1), (-1, 1)):
                p = np.zeros(3)
                p[axis], p[u], p[w] = sign * h, a * h, b * h
                quad.append(p)
            base = len(verts)
            verts += quad
            tri = [(0, 1, 2), (0, 2, 3)] if sign > 0 else [(0, 2, 1), (0, 3, 2)]
            faces += [(base + i, base + j, base + k) for i, j, k in tri]
    return TriMesh(np.array(verts), np.array(faces, dtype=np.int64), np.zeros(len(faces), bool))


def cylinder_mesh(radius: float, height: float, segments: int = CYLINDER_SEGMENTS) -> TriMesh:
    """Z-axis cylinder centred at the origin: smooth side, flat caps (unshared vertices)."""
    a = 2 * np.pi * np.arange(segments) / segments
    ring = np.stack([radius * np.cos(a), radius * np.sin(a)], axis=1)
    h = height / 2.0
    bot = np.column_stack([ring, np.full(segments, -h)])
    top = np.column_stack([ring, np.full(segments, h)])
    i = np.arange(segments)
    j = (i + 1) % segments
    # Side: vertices [bot | top], two triangles per segment.
    side_v = np.concatenate([bot, top])
    side_f = np.concatenate(
        [np.stack([i, j, segments + j], 1), np.stack([i, segments + j, segments + i], 1)]
    )
    # Caps: own ring copies plus a centre vertex each.
    off = len(side_v)
    cap_v = np.concatenate([bot, [[0.0, 0.0, -h]], top, [[0.0, 0.0, h]]])
    cb, ct = off + segments, off + 2 * segments + 1
    bot_f = np.stack([np.full(segments, cb), off + j, off + i], 1)
    top_f = np.stack([np.full(segments, ct), off + segments + 1 + i, off + segments + 1 + j], 1)
    verts = np.concatenate([side_v, cap_v])
    faces = np.concatenate([side_f, bot_f, top_f]).astype(np.int64)
    smooth = np.concatenate([np.ones(len(side_f), bool), np.zeros(2 * segments, bool)])
    return TriMesh(verts, faces, smooth)


def plane_mesh(size: float, z: float = 0.0) -> TriMesh:
    """Square ``size`` x ``size`` in the plane ``z``, centred at the origin, normal +z."""
    h = size / 2.0
    v = np.array([[-h, -h, z], [h, -h, z], [h, h, z], [-h, h, z]])
    f = np.array([[0, 1, 2], [0, 2, 3]], dtype=np.int64)
    return TriMesh(v, f, np.zeros(2, bool))


def box_mesh(lo, hi) -> TriMesh:
    """Axis-aligned box between corners ``lo`` and ``hi`` (flat shaded)."""
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    c = cube_mesh(1.0)
    v = (c.vertices + 0.5) * (hi - lo) + lo
    return TriMesh(v, c.faces, c.smooth)
