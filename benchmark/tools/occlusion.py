"""How much of each object another object hides in a view (diagnosis only).

The paper credits the self-attention among slots with keeping an occluded object in a slot
of its own: without it "an occluded object may be mistakenly segmented into the slot of
another object that corresponds to the occluded area". Counting that needs to know which
objects are occluded, and by whom, which the rendered masks do not say (they hold only the
visible pixels). A scene's JSON is enough to ray-cast it again without Blender
(``generators.raycast``): once with every object, once with each object alone. Rays go
through pixel centres at the resolution asked for (the model's, not the stored one).

``benchmark.tools.failures.failure_breakdown(..., occlusion=SplitOcclusion(test_dir, res))``
adds, per object, its hidden fraction and occluders, and the summary
:func:`summarize_occlusion`: the lost / merged / own fractions of the objects by how much of
them is hidden, and how often an occluded object shares its slot with one of its occluders.

Example (an object behind another one, seen from a camera on the +x axis):
    >>> import numpy as np
    >>> from generators import geometry
    >>> front = geometry.box_mesh((1.0, -0.5, 0.0), (1.5, 0.5, 1.0))
    >>> back = geometry.box_mesh((-1.0, -0.5, 0.0), (-0.5, 0.5, 1.0))
    >>> c2w = geometry.look_at_cam_to_world(np.array([8.0, 0, 0.5]), np.array([0, 0, 0.5]))
    >>> K = geometry.intrinsics(35.0, 32.0, 32, 32)
    >>> occ = view_occlusion([front, back], [1, 2], K, c2w, 32)
    >>> occ[1]["hidden"], occ[2]["hidden"] > 0.5, occ[2]["occluders"]
    (0.0, True, [1])
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np

from generators import geometry
from generators.raycast import intersector
from generators.spec import SceneSpec
from scenefmt import SplitLayout, read_json

#: Hidden-fraction bins of :func:`summarize_occlusion`: [lo, hi) of the part of an object's
#: silhouette that other objects cover.
BINS = (("visible", 0.0, 0.05), ("partly", 0.05, 0.5), ("mostly", 0.5, 1.01))


def _first_hit(meshes: list[geometry.TriMesh], ids: list[int], o, d) -> np.ndarray:
    """int [R]: the id of the first mesh each ray hits (-1: none)."""
    merged, owner = geometry.concat_meshes(meshes)
    face_ids = np.asarray(ids, dtype=np.int64)[owner]
    tri = intersector(merged).intersects_first(o, d)
    return np.where(tri >= 0, face_ids[np.maximum(tri, 0)], -1)


def view_occlusion(
    meshes: list[geometry.TriMesh], ids: list[int], K: np.ndarray, c2w: np.ndarray, res: int
) -> dict[int, dict[str, Any]]:
    """Per object: its silhouette alone, what of it shows, and who hides the rest.

    Args:
        meshes / ids: the objects' world-space meshes and their instance ids. Only objects
            occlude: :class:`SplitOcclusion` leaves the ground out (it hides no object from
            cameras above it; a room's walls, if they ever hid one, would not count).
        K / c2w: the view's intrinsics at ``res`` x ``res`` and camera-to-world matrix.
        res: square image size.

    Returns:
        ``{id: {"silhouette": pixels of the object cast alone, "visible": pixels where it is
        the first hit, "hidden": 1 - visible / silhouette (0 for an object outside the
        view), "occluders": ids covering its hidden pixels, most pixels first}}``.
    """
    o, d = geometry.pixel_rays(K, c2w, res, res)
    first = _first_hit(meshes, ids, o, d)
    out: dict[int, dict[str, Any]] = {}
    for mesh, oid in zip(meshes, ids, strict=True):
        alone = _first_hit([mesh], [oid], o, d) == oid
        sil, vis = int(alone.sum()), int((first == oid).sum())
        cover = first[alone & (first != oid) & (first >= 0)]
        who, n = np.unique(cover, return_counts=True)
        out[int(oid)] = {
            "silhouette": sil,
            "visible": vis,
            "hidden": 1.0 - vis / sil if sil else 0.0,
            "occluders": [int(w) for w in who[np.argsort(-n, kind="stable")]],
        }
    return out


class SplitOcclusion:
    """``(scene, view) -> view_occlusion`` of a generated split's scenes, at ``res``.

    ``scene`` is the ``sc%04d`` number (``MultiViewDataset.scene_ids``); the scene JSON is
    read and cast on each call (one view of each scene is what ``failure_breakdown`` asks for).
    """

    def __init__(self, root: str | Path, res: int) -> None:
        self.root, self.res = Path(root), int(res)
        layout = SplitLayout(self.root)
        self._json = layout.scene_json

    def __call__(self, scene: int, view: int) -> dict[int, dict[str, Any]]:
        path = self._json(scene)
        if not path.is_file():
            raise FileNotFoundError(f"{path}: no scene JSON; occlusion needs a generated split")
        spec = SceneSpec.from_json(read_json(path))
        v = spec.views[view]
        meshes = [ob.world_mesh() for ob in spec.objects]
        ids = [ob.instance_id for ob in spec.objects]
        return view_occlusion(meshes, ids, v.K(self.res, self.res), v.c2w(), self.res)


def summarize_occlusion(rows: list[dict[str, Any]]) -> dict[str, Any]:
    """Failure kinds by hidden fraction, over ``object_failures`` rows that carry ``hidden``,
    ``occluders`` and (merged rows) ``merged_with``.

    Returns, per bin of :data:`BINS`: ``objects``, the ``lost`` / ``merged`` / ``own``
    fractions and ``merged_into_occluder`` (the fraction of the bin's objects whose slot
    is shared with one of their occluders: the paper's failure); plus ``bins`` (the edges).
    NaN fractions where a bin is empty.
    """
    out: dict[str, Any] = {"bins": {name: [lo, min(hi, 1.0)] for name, lo, hi in BINS}}
    for name, lo, hi in BINS:
        group = [r for r in rows if lo <= r["hidden"] < hi]
        n = len(group)

        def frac(pred, group=group, n=n) -> float:
            return sum(1 for r in group if pred(r)) / n if n else math.nan

        out[name] = {
            "objects": n,
            **{k: frac(lambda r, k=k: r["kind"] == k) for k in ("lost", "merged", "own")},
            "merged_into_occluder": frac(
                lambda r: (
                    r["kind"] == "merged"
                    and bool(set(r.get("merged_with", [])) & set(r["occluders"]))
                )
            ),
        }
    return out
