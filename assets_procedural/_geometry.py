"""Closed-mesh building blocks for the procedural chairs (numpy only, no trimesh).

Every chair part is one *swept solid*: a star-shaped 2D profile carried along a
3D polyline with mitred joints and capped ends (or a closed loop without caps).
Boxes, cylinders, bent tubes, extruded outlines and curved panels are all sweeps,
so there is a single routine to get right: it returns a vertex/face pair that is
watertight by construction (shared ring vertices, fan caps around a centre
vertex) and whose faces are flipped, if needed, so the signed volume is positive
(outward normals).

Parts are returned as ``(V, F)`` with ``V`` float64 ``[n, 3]`` and ``F`` int64
``[m, 3]``; ``assets_procedural.chairs`` concatenates them into one mesh.
"""

from __future__ import annotations

import numpy as np

Part = tuple[np.ndarray, np.ndarray]

_EPS = 1e-12


def _unit(v: np.ndarray) -> np.ndarray:
    n = float(np.linalg.norm(v))
    if n < _EPS:
        raise ValueError(f"cannot normalise a zero-length vector {v!r}")
    return v / n


def _rotate_min(vec: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Apply the minimal rotation taking unit vector ``a`` to unit ``b`` to ``vec``."""
    axis = np.cross(a, b)
    s = float(np.linalg.norm(axis))
    c = float(np.dot(a, b))
    if s < 1e-12:
        return vec  # parallel (antiparallel paths are rejected by the caller)
    axis = axis / s
    return vec * c + np.cross(axis, vec) * s + axis * float(np.dot(axis, vec)) * (1.0 - c)


def signed_volume(v: np.ndarray, f: np.ndarray) -> float:
    """Signed volume of a closed triangle mesh (positive for outward normals)."""
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    return float(np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6.0)


def rect_profile(w: float, h: float) -> np.ndarray:
    """Rectangle profile ``[4, 2]``: ``w`` along the frame's u axis, ``h`` along v."""
    return np.array([[-w / 2, -h / 2], [w / 2, -h / 2], [w / 2, h / 2], [-w / 2, h / 2]])


def circle_profile(r: float, n: int = 8) -> np.ndarray:
    """Regular ``n``-gon profile ``[n, 2]`` of circumradius ``r``."""
    a = (np.arange(n) + 0.5) * (2 * np.pi / n)
    return np.stack([r * np.cos(a), r * np.sin(a)], axis=1)


def superellipse(a: float, b: float, exponent: float, n: int = 24) -> np.ndarray:
    """Superellipse ``|x/a|^e + |y/b|^e = 1`` sampled at ``n`` points ``[n, 2]`` (CCW)."""
    t = (np.arange(n) + 0.5) * (2 * np.pi / n)
    c, s = np.cos(t), np.sin(t)
    p = 2.0 / exponent
    return np.stack([a * np.sign(c) * np.abs(c) ** p, b * np.sign(s) * np.abs(s) ** p], axis=1)


def round_corners(path: np.ndarray, radius: float, n: int = 3) -> np.ndarray:
    """Replace each interior corner of a polyline by ``n`` points on a quadratic Bezier.

    The corner cut-back is ``radius`` clipped to 45% of the shorter adjacent segment,
    so consecutive fillets never overlap.
    """
    path = np.asarray(path, dtype=np.float64)
    if len(path) < 3 or radius <= 0:
        return path
    out = [path[0]]
    for k in range(1, len(path) - 1):
        p0, p, p1 = path[k - 1], path[k], path[k + 1]
        d0, d1 = p - p0, p1 - p
        l0, l1 = np.linalg.norm(d0), np.linalg.norm(d1)
        r = min(radius, 0.45 * l0, 0.45 * l1)
        a = p - d0 / l0 * r
        b = p + d1 / l1 * r
        t = np.linspace(0.0, 1.0, n)[:, None]
        out.extend((1 - t) ** 2 * a + 2 * (1 - t) * t * p + t**2 * b)
    out.append(path[-1])
    return np.asarray(out)


def sweep(
    path: np.ndarray,
    profile: np.ndarray,
    ref: np.ndarray | tuple[float, float, float] = (1.0, 0.0, 0.0),
    closed: bool = False,
) -> Part:
    """Sweep a 2D profile along a 3D polyline into a closed solid.

    Args:
        path: ``[M, 3]`` polyline (``M >= 2``; ``M >= 3`` when ``closed``). Consecutive
            points must differ and turns must be below ~150 degrees.
        profile: ``[P, 2]`` polygon, star-shaped around its centroid. Its first
            coordinate runs along ``u`` (``ref`` projected perpendicular to the first
            segment), its second along ``v = tangent x u``.
        ref: reference direction fixing the profile's roll at the start.
        closed: the path is a loop (last point joins the first); no caps.

    Returns:
        ``(V, F)``: float64 ``[n, 3]`` vertices and int64 ``[m, 3]`` faces, watertight,
        outward-oriented (positive signed volume).
    """
    path = np.asarray(path, dtype=np.float64)
    prof = np.asarray(profile, dtype=np.float64)
    pts = np.vstack([path, path[:1]]) if closed else path
    seg = np.diff(pts, axis=0)
    seglen = np.linalg.norm(seg, axis=1)
    if np.any(seglen < 1e-9):
        raise ValueError("sweep path has coincident consecutive points")
    tan = seg / seglen[:, None]
    n_seg = len(tan)
    m = len(path)
    p = len(prof)

    ref = np.asarray(ref, dtype=np.float64)
    u = ref - tan[0] * float(np.dot(ref, tan[0]))
    if np.linalg.norm(u) < 1e-6:
        alt = np.array([0.0, 1.0, 0.0]) if abs(tan[0][1]) < 0.9 else np.array([0.0, 0.0, 1.0])
        u = alt - tan[0] * float(np.dot(alt, tan[0]))
    u = _unit(u)

    # Parallel-transport the profile's u axis from segment to segment (minimal
    # rotation), so bent tubes do not twist; ring k uses its incoming segment's frame.
    frames = [u]
    for k in range(1, n_seg):
        frames.append(_unit(_rotate_min(frames[-1], tan[k - 1], tan[k])))

    rings = np.empty((m, p, 3))
    for k in range(m):
        if closed:
            # k=0: the incoming segment is the closing one (index -1).
            t_in, t_out = tan[k - 1], tan[k]
            uk = frames[k - 1]
        elif k == 0:
            t_in = t_out = tan[0]
            uk = frames[0]
        elif k == m - 1:
            t_in = t_out = tan[-1]
            uk = frames[-1]
        else:
            t_in, t_out = tan[k - 1], tan[k]
            uk = frames[k - 1]
        bis = t_in + t_out
        if np.linalg.norm(bis) < 0.5:
            raise ValueError("sweep path turns back on itself (turn above ~150 degrees)")
        nrm = _unit(bis)
        vk = np.cross(t_in, uk)
        offs = prof[:, :1] * uk + prof[:, 1:] * vk
        s = -(offs @ nrm) / float(np.dot(t_in, nrm))
        rings[k] = pts[k] + offs + s[:, None] * t_in

    verts = rings.reshape(-1, 3)
    i = np.arange(p)
    j = (i + 1) % p
    n_bands = m if closed else m - 1
    k = np.arange(n_bands)[:, None]
    k1 = (k + 1) % m
    a = k * p + i
    b = k * p + j
    c = k1 * p + j
    d = k1 * p + i
    side = np.concatenate(
        [np.stack([a, b, c], -1).reshape(-1, 3), np.stack([a, c, d], -1).reshape(-1, 3)]
    )
    if closed:
        faces = side
    else:
        c0 = len(verts)
        c1 = c0 + 1
        centres = np.stack([rings[0].mean(0), rings[-1].mean(0)])
        verts = np.vstack([verts, centres])
        last = (m - 1) * p
        cap0 = np.stack([np.full(p, c0), j, i], -1)
        cap1 = np.stack([np.full(p, c1), last + i, last + j], -1)
        faces = np.concatenate([side, cap0, cap1])
    faces = faces.astype(np.int64)
    if signed_volume(verts, faces) < 0:
        faces = faces[:, ::-1].copy()
    return verts, faces


def tube(a, b, profile: np.ndarray, ref=(1.0, 0.0, 0.0)) -> Part:
    """Straight sweep from point ``a`` to point ``b``."""
    return sweep(np.array([a, b], dtype=np.float64), profile, ref)


def box(center, size) -> Part:
    """Axis-aligned box with the given centre ``[3]`` and full size ``[3]``."""
    cx, cy, cz = center
    sx, sy, sz = size
    return tube((cx, cy, cz - sz / 2), (cx, cy, cz + sz / 2), rect_profile(sx, sy))


def plate(outline: np.ndarray, origin, e1, e2, thickness: float) -> Part:
    """Extrude a 2D outline lying in the plane ``origin + x*e1 + y*e2``.

    The slab is ``thickness`` thick, centred on that plane; ``e1``/``e2`` must be
    orthonormal. The outline must be star-shaped around its centroid.
    """
    e1 = _unit(np.asarray(e1, dtype=np.float64))
    e2 = _unit(np.asarray(e2, dtype=np.float64))
    n = np.cross(e1, e2)
    o = np.asarray(origin, dtype=np.float64)
    return tube(o - n * thickness / 2, o + n * thickness / 2, outline, ref=e1)
