"""The split's JSON records: the scene record (``sc%04d.json``), the manifest
(``manifest.json``) and the dataset fingerprint over both.

Where this sits: every writer (``generators.writer``, ``generators.manip_writer``,
``svorf.synthetic``) builds a :class:`SceneRecord` and a :class:`Manifest` and writes
their :meth:`~SceneRecord.to_json`; every reader (``svorf.data``, ``generate verify``, the
benchmark's dataset bookkeeping) reads them back with ``from_json``. The fields a reader
relies on are typed; what only one writer records (the generator's sampling draws,
materials, lights, render settings, the grayscale and manipulation records) travels in
``extra`` unchanged, so ``to_json`` gives back exactly the dict that was read.

Files written before these classes read the same: a missing ``camera_convention`` is
``"opencv"``, a missing ``depth`` ``"planar_z"``, and a manifest's ``resolution`` may be an
int (square views, the generator) or ``[h, w]`` (``svorf.synthetic``); use
:attr:`Manifest.image_hw` for both.
"""

from __future__ import annotations

import hashlib
import json
import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from scenefmt.layout import FORMAT_VERSION

__all__ = [
    "MANIFEST_FORMAT",
    "SCENE_FORMAT",
    "Manifest",
    "SceneRecord",
    "ViewRecord",
    "dataset_fingerprint",
    "legacy_fingerprint",
]

#: ``format`` of a scene record and of a generator's manifest.
SCENE_FORMAT = "svorf-scene"
MANIFEST_FORMAT = "svorf-dataset"


def _matrix(value: Any, shape: tuple[int, int], what: str) -> tuple[tuple[Any, ...], ...]:
    """``value`` as a tuple of row tuples of ``shape``, the entries kept as they are."""
    try:
        rows = tuple(tuple(r) for r in value)
    except TypeError as e:
        raise ValueError(f"{what}: expected a {shape[0]}x{shape[1]} matrix, got {value!r}") from e
    if len(rows) != shape[0] or any(len(r) != shape[1] for r in rows):
        got = f"{len(rows)} rows of {sorted({len(r) for r in rows})}"
        raise ValueError(f"{what}: expected a {shape[0]}x{shape[1]} matrix, got {got}")
    return rows


def _object(d: Any, what: str) -> Mapping[str, Any]:
    if not isinstance(d, Mapping):
        raise ValueError(f"{what}: expected a JSON object, got {type(d).__name__}")  # noqa: TRY004 - a data problem
    return d


@dataclass(frozen=True)
class ViewRecord:
    """One camera of a scene record.

    Attributes:
        image: the view's RGB file name (``SplitLayout.rgb(scene, view).name``).
        K: 3x3 pixel intrinsics at the split's resolution (pixel centres at +0.5).
        cam_to_world: 4x4 camera-to-world, OpenCV axes (x right, y down, z forward).
        extra: the writer's other keys (``azimuth_deg``, ``elevation_deg``, ``radius``,
            ``look_at``, ``lens_mm``, ``sensor_width_mm``, ``sensor_fit``, ...).
    """

    image: str
    K: tuple[tuple[float, ...], ...]
    cam_to_world: tuple[tuple[float, ...], ...]
    extra: Mapping[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        object.__setattr__(self, "K", _matrix(self.K, (3, 3), "K"))
        object.__setattr__(self, "cam_to_world", _matrix(self.cam_to_world, (4, 4), "cam_to_world"))
        object.__setattr__(self, "extra", dict(self.extra))

    def to_json(self) -> dict[str, Any]:
        return {
            **self.extra,
            "image": self.image,
            "K": [list(r) for r in self.K],
            "cam_to_world": [list(r) for r in self.cam_to_world],
        }

    @classmethod
    def from_json(cls, d: Any) -> ViewRecord:
        """Raises ValueError naming the missing or malformed field."""
        d = _object(d, "view")
        for key in ("K", "cam_to_world"):
            if key not in d:
                raise ValueError(f"view: no {key!r}")
        known = {"image", "K", "cam_to_world"}
        return cls(
            image=str(d.get("image", "")),
            K=d["K"],
            cam_to_world=d["cam_to_world"],
            extra={k: v for k, v in d.items() if k not in known},
        )


@dataclass(frozen=True)
class SceneRecord:
    """The scene record ``sc%04d.json``: what a scene holds and where its cameras are.

    Attributes:
        preset / split / index / seed: where the scene sits (dataset seed, not the scene's).
        views: one :class:`ViewRecord` per view, in view order.
        objects: one JSON object per instance; ``objects[k - 1]`` has ``instance_id`` k.
        camera_convention: ``"opencv"`` (the only one written).
        depth: ``"planar_z"`` (the only one written): ``depth/*.exr`` holds camera z.
        extra: every other top-level key, unchanged (the generator's ``scene_seed``,
            ``attempt``, ``rng``, ``lights``, ``materials``, ``ground``, ``world``,
            ``render``, ``grayscale``, ``manipulation``, ...).
    """

    preset: str
    split: str
    index: int
    seed: int
    views: tuple[ViewRecord, ...]
    objects: tuple[Any, ...] = ()
    camera_convention: str = "opencv"
    depth: str = "planar_z"
    extra: Mapping[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        object.__setattr__(self, "views", tuple(self.views))
        object.__setattr__(self, "objects", tuple(self.objects))
        object.__setattr__(self, "extra", dict(self.extra))

    @property
    def n_views(self) -> int:
        return len(self.views)

    def to_json(self) -> dict[str, Any]:
        """The JSON object written to ``sc%04d.json`` (written with sorted keys)."""
        return {
            "format": SCENE_FORMAT,
            **self.extra,
            "preset": self.preset,
            "split": self.split,
            "index": self.index,
            "seed": self.seed,
            "camera_convention": self.camera_convention,
            "depth": self.depth,
            "objects": list(self.objects),
            "views": [v.to_json() for v in self.views],
        }

    @classmethod
    def from_json(cls, d: Any) -> SceneRecord:
        """Read a scene record (also the files written before this class).

        Raises:
            ValueError: not a JSON object, no ``views`` list, or a view without a 3x3 ``K``
                or a 4x4 ``cam_to_world`` (the message names the view and the field).
        """
        d = _object(d, "scene record")
        views = d.get("views")
        if not isinstance(views, list):
            got = type(views).__name__
            raise ValueError(f"scene record: 'views' must be a list, got {got}")  # noqa: TRY004
        parsed = []
        for i, v in enumerate(views):
            try:
                parsed.append(ViewRecord.from_json(v))
            except ValueError as e:
                raise ValueError(f"view {i}: {e}") from e
        known = {"format", "preset", "split", "index", "seed", "camera_convention", "depth"}
        known |= {"objects", "views"}
        return cls(
            preset=d.get("preset", ""),
            split=d.get("split", ""),
            index=d.get("index", -1),
            seed=d.get("seed", 0),
            views=tuple(parsed),
            objects=tuple(d.get("objects") or ()),
            camera_convention=d.get("camera_convention", "opencv"),
            depth=d.get("depth", "planar_z"),
            extra={k: v for k, v in d.items() if k not in known},
        )


@dataclass(frozen=True)
class Manifest:
    """``manifest.json``: what a split folder holds.

    Attributes:
        preset / split: the dataset preset and split name.
        n_scenes: scenes the split holds when complete.
        n_views: views per scene.
        resolution: square image side in pixels, or ``(h, w)`` (``svorf.synthetic``'s
            manifests); :attr:`image_hw` reads both.
        seed: dataset seed.
        generator: what wrote the split (``"generators 0.1.0"``, ``"svorf.synthetic"``).
        conventions: plain-words conventions (camera, depth, ids, mask levels).
        format_version: :data:`scenefmt.FORMAT_VERSION` when written.
        status: ``"in_progress"`` / ``"complete"`` (the generator), None = not recorded.
        extra: every other key, unchanged (``format``, ``description``, ``render``,
            ``preset_config``, ``files``, ``manip``, ...).
    """

    preset: str
    split: str
    n_scenes: int
    n_views: int
    resolution: int | tuple[int, int]
    seed: int
    generator: str
    conventions: Mapping[str, Any] = field(default_factory=dict)
    format_version: str = FORMAT_VERSION
    status: str | None = None
    extra: Mapping[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if not isinstance(self.resolution, int):
            object.__setattr__(self, "resolution", tuple(self.resolution))
        object.__setattr__(self, "conventions", dict(self.conventions))
        object.__setattr__(self, "extra", dict(self.extra))

    @property
    def image_hw(self) -> tuple[int, int]:
        """``(h, w)`` of the split's views."""
        r = self.resolution
        return (int(r), int(r)) if isinstance(r, int) else (int(r[0]), int(r[1]))

    def to_json(self) -> dict[str, Any]:
        """The JSON object written to ``manifest.json`` (written with sorted keys)."""
        d: dict[str, Any] = {
            **self.extra,
            "format_version": self.format_version,
            "preset": self.preset,
            "split": self.split,
            "n_scenes": self.n_scenes,
            "n_views": self.n_views,
            "resolution": self.resolution
            if isinstance(self.resolution, int)
            else list(self.resolution),
            "seed": self.seed,
            "generator": self.generator,
            "conventions": dict(self.conventions),
        }
        if self.status is not None:
            d["status"] = self.status
        return d

    @classmethod
    def from_json(cls, d: Any) -> Manifest:
        """Read a manifest (also the files written before this class).

        Raises:
            ValueError: not a JSON object, or ``n_scenes`` / ``n_views`` / ``resolution``
                missing or not integers (``resolution`` may be ``[h, w]``).
        """
        d = _object(d, "manifest")
        out: dict[str, Any] = {}
        for key in ("n_scenes", "n_views"):
            if not isinstance(d.get(key), int) or isinstance(d.get(key), bool):
                got = d.get(key)
                raise ValueError(f"manifest: {key!r} must be an integer, got {got!r}")  # noqa: TRY004
            out[key] = d[key]
        res = d.get("resolution")
        ok = isinstance(res, int) and not isinstance(res, bool)
        if not ok and not (
            isinstance(res, Sequence) and len(res) == 2 and all(isinstance(x, int) for x in res)
        ):
            raise ValueError(f"manifest: 'resolution' must be an integer or [h, w], got {res!r}")
        known = {"format_version", "preset", "split", "n_scenes", "n_views", "resolution"}
        known |= {"seed", "generator", "conventions", "status"}
        return cls(
            preset=d.get("preset", ""),
            split=d.get("split", ""),
            resolution=res,
            seed=d.get("seed", 0),
            generator=d.get("generator", ""),
            conventions=d.get("conventions") or {},
            format_version=d.get("format_version", ""),
            status=d.get("status"),
            extra={k: v for k, v in d.items() if k not in known},
            **out,
        )


#: Decimal places a number keeps in :func:`dataset_fingerprint`. A record's floats are
#: computed from the scene's seed, but the BLAS kernels numpy picks for the CPU (OpenBLAS's
#: Haswell kernels on an AVX2 machine, SkylakeX on an AVX-512 one) round differently, so
#: the same scene's camera matrices written on two machines differ by up to ~2e-16 (and a
#: computed zero may be 1e-17). 1e-6 world units is far below any difference between two
#: scenes, and coarse enough that such noise almost never straddles a rounding boundary:
#: noise of 2e-15 does so with probability 2e-9 per number, so even if all ~200,000
#: numbers of a 1,000-scene split carried it, the chance of a changed fingerprint is
#: below 0.001.
FINGERPRINT_DECIMALS = 6


def _number(x: float) -> str:
    """``x`` rounded to FINGERPRINT_DECIMALS places, as text (-0 written as 0)."""
    return format(round(x, FINGERPRINT_DECIMALS) + 0.0, ".15g")


def _canonical(value: Any) -> Any:
    """``value`` (parsed JSON) with every float as the text of :func:`_number`."""
    if isinstance(value, float):
        return _number(value)
    if isinstance(value, dict):
        return {k: _canonical(v) for k, v in value.items()}
    if isinstance(value, list):
        return [_canonical(v) for v in value]
    return value


def _canonical_bytes(path: Path) -> bytes:
    """The bytes of a record as the fingerprint sees them: JSON parsed and rewritten in
    canonical form (sorted keys, floats rounded); a text file's numbers rounded the same
    way (uORF ``_RT.txt``); anything unparsable as it is."""
    raw = path.read_bytes()
    if path.suffix == ".json":
        try:
            obj = json.loads(raw)
        except ValueError:
            return raw
        return json.dumps(_canonical(obj), sort_keys=True, separators=(",", ":")).encode()
    words = []
    for word in raw.decode("utf-8", "replace").split():
        try:
            words.append(_number(float(word)))
        except ValueError:
            words.append(word)
    return " ".join(words).encode()


def dataset_fingerprint(root: str | os.PathLike) -> str:
    """SHA-256 over ``manifest.json`` and every ``sc*.json`` of a split (hex string).

    The scene records hold every random draw and camera, so two folders with the same
    fingerprint hold the same scenes (render noise aside). Numbers enter rounded to
    :data:`FINGERPRINT_DECIMALS` decimal places and JSON in canonical form, so the same
    split generated on two machines (whose floating-point libraries may differ in the last
    bit) has one fingerprint. For uORF-layout folders (no JSON) the hash runs over the
    sorted ``_RT.txt`` names and their numbers.
    """
    return _fingerprint(Path(root), _canonical_bytes)


def legacy_fingerprint(root: str | os.PathLike) -> str:
    """The fingerprint as written before 2026-11-27 (raw bytes, no rounding): lets a
    checkpoint written then be resumed on the split it was trained on."""
    return _fingerprint(Path(root), Path.read_bytes)


def _fingerprint(root: Path, content: Any) -> str:
    h = hashlib.sha256()
    files = [root / "manifest.json"] if (root / "manifest.json").is_file() else []
    files += sorted(root.glob("sc[0-9][0-9][0-9][0-9].json"))
    if not files:
        files = sorted(root.glob("*_RT.txt"))
    for p in files:
        h.update(p.name.encode() + b"\0")
        h.update(content(p) + b"\0")
    return h.hexdigest()
