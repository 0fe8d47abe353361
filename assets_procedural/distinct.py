"""Geometric descriptors of chairs and a distinctness count over a pool of ids.

Where this sits: ``room-diverse`` promises a pool of at least 1,200 procedural
chair shapes; this module checks that promise. ``chair_descriptor`` summarises a
mesh in a fixed-length, scale-free vector; ``count_distinct`` calls two chairs
the same when *every* descriptor entry agrees within ``tol`` (Chebyshev
distance <= tol) and counts the classes of that relation (transitively closed).

Command line::

    python -m assets_procedural.distinct --n 1200
    # -> 1200 chair ids -> 1200 geometrically distinct meshes (tol 0.01), 12.3 s

Descriptor layout (``DESCRIPTOR_NAMES``), all computed on the mesh as given
(chairs are already in the canonical frame, so the numbers are comparable):

* ``extent_x, extent_y, extent_z`` (bounding box; one of x/y is 1.0),
* ``volume_ratio``: sum of part volumes / bounding-box volume,
* ``area_ratio``: surface area / bounding-box surface area,
* ``n_parts``: connected components (an integer: any difference counts),
* ``vol_centroid_{x,y,z}``: volume centroid in box-normalised coordinates [0, 1],
* ``area_moment_{xx,yy,zz,xy,xz,yz}``: second central moments of the surface
  (area-weighted face centroids, box-normalised),
* ``area_hist_{i}`` (64): area fraction of the surface in each cell of a 4x4x4
  grid over the bounding box (a coarse occupancy map of where the parts are).
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field

import numpy as np
import trimesh
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from assets_procedural.chairs import chair_mesh

HIST_BINS = 4
DESCRIPTOR_NAMES: tuple[str, ...] = (
    ("extent_x", "extent_y", "extent_z", "volume_ratio", "area_ratio", "n_parts")
    + tuple(f"vol_centroid_{a}" for a in "xyz")
    + tuple(f"area_moment_{a}" for a in ("xx", "yy", "zz", "xy", "xz", "yz"))
    + tuple(f"area_hist_{i}" for i in range(HIST_BINS**3))
)
DEFAULT_TOL = 0.01


def _n_components(n_vertices: int, faces: np.ndarray) -> int:
    """Number of connected components among vertices used by ``faces``."""
    rows = np.concatenate([faces[:, 0], faces[:, 1]])
    cols = np.concatenate([faces[:, 1], faces[:, 2]])
    adj = coo_matrix(
        (np.ones(len(rows), dtype=np.int8), (rows, cols)), shape=(n_vertices, n_vertices)
    )
    _, labels = connected_components(adj, directed=False)
    used = np.zeros(n_vertices, dtype=bool)
    used[faces.ravel()] = True
    return len(np.unique(labels[used]))


def chair_descriptor(mesh: trimesh.Trimesh) -> np.ndarray:
    """Scale-free shape descriptor of a (chair) mesh.

    Args:
        mesh: closed-per-part triangle mesh (e.g. ``chair_mesh(i)``).

    Returns:
        float64 ``[len(DESCRIPTOR_NAMES)]`` (= 79) vector; see the module docstring.

    Raises:
        ValueError: the mesh has no faces or a flat bounding box.
    """
    v = np.asarray(mesh.vertices, dtype=np.float64)
    f = np.asarray(mesh.faces, dtype=np.int64)
    if len(f) == 0:
        raise ValueError("chair_descriptor: mesh has no faces")
    lo, hi = v.min(0), v.max(0)
    ext = hi - lo
    if np.any(ext <= 0):
        raise ValueError(f"chair_descriptor: degenerate bounding box extents {ext}")
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    cr = np.cross(b - a, c - a)
    area_f = 0.5 * np.linalg.norm(cr, axis=1)
    area = area_f.sum()
    # Signed tetra volumes against the box corner (closed parts -> sum of part volumes).
    a0, b0, c0 = a - lo, b - lo, c - lo
    vol_t = np.einsum("ij,ij->i", a0, np.cross(b0, c0)) / 6.0
    vol = vol_t.sum()
    box_vol = float(np.prod(ext))
    box_area = 2.0 * float(ext[0] * ext[1] + ext[0] * ext[2] + ext[1] * ext[2])
    vol_centroid = (
        ((vol_t[:, None] * (a0 + b0 + c0) / 4.0).sum(0) / vol) / ext if vol != 0 else np.zeros(3)
    )
    cen = ((a + b + c) / 3.0 - lo) / ext  # box-normalised face centroids in [0, 1]
    w = area_f / area
    mu = (w[:, None] * cen).sum(0)
    d = cen - mu
    mom = np.array(
        [
            (w * d[:, 0] ** 2).sum(),
            (w * d[:, 1] ** 2).sum(),
            (w * d[:, 2] ** 2).sum(),
            (w * d[:, 0] * d[:, 1]).sum(),
            (w * d[:, 0] * d[:, 2]).sum(),
            (w * d[:, 1] * d[:, 2]).sum(),
        ]
    )
    cell = np.clip((cen * HIST_BINS).astype(np.int64), 0, HIST_BINS - 1)
    flat = (cell[:, 0] * HIST_BINS + cell[:, 1]) * HIST_BINS + cell[:, 2]
    hist = np.bincount(flat, weights=w, minlength=HIST_BINS**3)
    out = np.concatenate(
        [
            ext,
            [vol / box_vol, area / box_area, float(_n_components(len(v), f))],
            vol_centroid,
            mom,
            hist,
        ]
    )
    assert out.shape == (len(DESCRIPTOR_NAMES),)
    return out


@dataclass
class DistinctDetails:
    """What :func:`count_distinct` found."""

    n_ids: int
    tol: float
    groups: list[list[int]] = field(default_factory=list)  #: ids judged identical (size > 1)
    min_distance: float = float("inf")  #: smallest Chebyshev distance between two ids
    closest_pair: tuple[int, int] | None = None
    seconds_build: float = 0.0  #: building meshes + descriptors
    seconds_compare: float = 0.0


def _close_pairs(desc: np.ndarray, tol: float, chunk: int = 64):
    """Pairs ``(i, j)``, ``i < j``, with Chebyshev distance <= ``tol``, and the closest pair.

    Returns:
        ``(pairs, (min_distance, (i, j) or None))``.
    """
    n = len(desc)
    best: tuple[float, tuple[int, int] | None] = (float("inf"), None)
    pairs: list[tuple[int, int]] = []
    cols = np.arange(n)
    for s in range(0, n, chunk):
        blk = desc[s : s + chunk]
        rows = np.arange(s, s + len(blk))
        dist = np.abs(blk[:, None, :] - desc[None, :, :]).max(-1)  # [chunk, n]
        dist = np.where(cols[None, :] > rows[:, None], dist, np.inf)  # keep j > i only
        r, c = divmod(int(np.argmin(dist)), n)
        if dist[r, c] < best[0]:
            best = (float(dist[r, c]), (int(rows[r]), int(c)))
        ii, jj = np.nonzero(dist <= tol)
        pairs.extend(zip(rows[ii].tolist(), jj.tolist()))
    return pairs, best


def count_distinct(ids: Iterable[int], tol: float = DEFAULT_TOL) -> tuple[int, DistinctDetails]:
    """Count geometrically distinct chairs among ``ids``.

    Two chairs are the same when all their descriptor entries differ by at most
    ``tol``; classes are the connected components of that relation.

    Args:
        ids: chair ids (duplicates in the list count as the same chair twice).
        tol: absolute tolerance on every descriptor entry (``>= 0``).

    Returns:
        ``(n_distinct, details)``.
    """
    id_list = [int(i) for i in ids]
    if tol < 0:
        raise ValueError(f"tol must be >= 0, got {tol}")
    if not id_list:
        return 0, DistinctDetails(n_ids=0, tol=tol)
    t0 = time.perf_counter()
    desc = np.stack([chair_descriptor(chair_mesh(i)) for i in id_list])
    t1 = time.perf_counter()
    pairs, (dmin, pair) = _close_pairs(desc, tol)
    n = len(id_list)
    if pairs:
        pi, pj = np.array(pairs).T
        adj = coo_matrix((np.ones(len(pi)), (pi, pj)), shape=(n, n))
        n_distinct, labels = connected_components(adj, directed=False)
    else:
        n_distinct, labels = n, np.arange(n)
    groups = []
    for lab in np.unique(labels):
        members = np.nonzero(labels == lab)[0]
        if len(members) > 1:
            groups.append([id_list[m] for m in members])
    t2 = time.perf_counter()
    details = DistinctDetails(
        n_ids=n,
        tol=tol,
        groups=groups,
        min_distance=dmin,
        closest_pair=None if pair is None else (id_list[pair[0]], id_list[pair[1]]),
        seconds_build=t1 - t0,
        seconds_compare=t2 - t1,
    )
    return int(n_distinct), details


def main(argv: Sequence[str] | None = None) -> int:
    """CLI: count distinct chairs among ids ``start .. start+n-1``; exit 1 if any clash."""
    ap = argparse.ArgumentParser(description="Count geometrically distinct procedural chairs.")
    ap.add_argument("--n", type=int, default=1200, help="number of chair ids (default 1200)")
    ap.add_argument("--start", type=int, default=0, help="first chair id (default 0)")
    ap.add_argument(
        "--tol",
        type=float,
        default=DEFAULT_TOL,
        help=f"descriptor tolerance (default {DEFAULT_TOL})",
    )
    args = ap.parse_args(argv)
    if args.n < 1 or args.start < 0:
        ap.error(f"--n must be >= 1 and --start >= 0, got --n {args.n} --start {args.start}")
    t0 = time.perf_counter()
    n_distinct, det = count_distinct(range(args.start, args.start + args.n), args.tol)
    dt = time.perf_counter() - t0
    print(
        f"{args.n} chair ids -> {n_distinct} geometrically distinct meshes "
        f"(tol {args.tol:g} on {len(DESCRIPTOR_NAMES)} descriptors), {dt:.1f} s"
    )
    if det.closest_pair is not None:
        print(f"closest pair {det.closest_pair}: Chebyshev distance {det.min_distance:.4f}")
    for grp in det.groups[:10]:
        print(f"same shape: {grp}")
    return 0 if n_distinct == args.n else 1


if __name__ == "__main__":
    raise SystemExit(main())
