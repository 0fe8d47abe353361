"""Datasets a protocol needs: find them on disk or generate them, and fingerprint them.

Where this sits: first step of every protocol. A dataset is one split folder in
the :mod:`scenefmt` contract at ``<data>/<scale>/<preset>/<split>``. When it is
missing (or incomplete) it is made:

- ``source="generator"`` (default): the Blender generator's importable function
  ``generators.dataset.generate_dataset(cfg)`` with the preset's rules, the
  scale's scene count, resolution and render samples. Generation resumes: scenes
  already complete on disk are not rendered again.
- ``source="synthetic"``: ``svorf.synthetic.write_synthetic_split`` analytic
  sphere scenes; a stand-in for tests and machines without ``bpy``. Reports say
  so in each dataset's ``source`` and in a note.

Existing splits (e.g. rendered by hand with ``generate``) are reused, never silently:

- a split with at least the scale's scene count is used; one with fewer scenes is
  extended by the generator when it was made with the scale's render settings and
  seed (scene i does not depend on the count), else (the generator would refuse to
  mix render settings) it is used as found when all of its own scenes are complete;
- whatever is used, its actual scene count, resolution, render samples, denoising and
  seed come from its manifest into the report, with ``deviations`` from the scale's
  nominal settings; a deviating split not generated in this run is first checked with
  ``generators.verify.verify_split`` (problems are an error);
- another resolution than the scale's is an error. A model whose training asks for finer
  images (``TrainConfig.target_size``) trains on a split of its own at that resolution,
  ``<data>/<scale>-<res>px/<preset>/<split>`` (:func:`at_resolution`): the same scenes,
  rendered finer; the scale's own splits are untouched.

The fingerprint (SHA-256 over ``manifest.json`` and the scene JSONs, via the
adapter) goes into the model cache key and into the report.
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from benchmark import adapter
from benchmark.scales import ScaleSettings
from scenefmt import (
    LUMA_REC601,
    Manifest,
    SplitLayout,
    is_scene_complete,
    read_json,
    read_rgb,
    write_rgb,
)

__all__ = [
    "DATA_SOURCES",
    "DatasetInfo",
    "SplitState",
    "dataset_dir",
    "ensure_dataset",
    "source_of",
    "split_state",
]

DATA_SOURCES = ("generator", "synthetic")

# Synthetic stand-ins: object counts (spheres; the analytic writer places them in a
# +-2.5 square) and seed offsets so that every preset/split differs.
_SYNTH_OBJECTS = {
    "clevr567": (3, 4),
    "clevr567-heldout": (3, 4),
    "clevr567-gray": (3, 4),
    "packed-clevr11": (5, 6),
    "room-chair": (2, 3),
    "room-diverse": (3, 3),
}
_SPLIT_SEED = {"train": 0, "test": 1}


@dataclass(frozen=True)
class DatasetInfo:
    """A split folder ready for training or evaluation."""

    name: str
    preset: str
    split: str
    path: Path
    fingerprint: str
    n_scenes: int
    n_views: int
    resolution: int
    source: str
    generated_now: bool
    wall_s: float
    render_samples: int | None = None
    denoise: bool | None = None
    data_seed: int | None = None
    nominal: dict[str, Any] = field(default_factory=dict)
    deviations: tuple[str, ...] = ()

    def to_report(self) -> dict[str, Any]:
        return {
            "name": self.name,
            "preset": self.preset,
            "split": self.split,
            "path": str(self.path),
            "fingerprint": self.fingerprint,
            "n_scenes": self.n_scenes,
            "n_views": self.n_views,
            "resolution": self.resolution,
            "source": self.source,
            "render_samples": self.render_samples,
            "denoise": self.denoise,
            "data_seed": self.data_seed,
            "nominal": dict(self.nominal),
            "deviations": list(self.deviations),
            "generated_now": self.generated_now,
        }


def dataset_dir(data_root: str | os.PathLike, scale: str, preset: str, split: str) -> Path:
    """``<data>/<scale>/<preset>/<split>``."""
    return Path(data_root) / scale / preset / split


def at_resolution(settings: ScaleSettings, resolution: int | None) -> ScaleSettings:
    """The scale's settings for splits rendered at ``resolution`` instead of the scale's
    (None or the same: ``settings`` itself). Their name, and so their folder, is
    ``<scale>-<res>px``: the same scenes and render settings, kept apart from the scale's
    own splits."""
    if resolution is None or int(resolution) == settings.resolution:
        return settings
    return replace(
        settings, name=f"{settings.name}-{int(resolution)}px", resolution=int(resolution)
    )


def _complete(root: Path, n_scenes: int, resolution: int) -> tuple[bool, str]:
    """Whether ``root`` holds ``n_scenes`` complete scenes at ``resolution``."""
    manifest = root / "manifest.json"
    if not manifest.is_file():
        return False, "no manifest.json"
    try:
        m = Manifest.from_json(read_json(manifest))
    except (OSError, ValueError) as err:
        return False, f"unreadable manifest ({err})"
    res = m.image_hw[0]
    if res != resolution:
        raise ValueError(
            f"{root}: holds {res}x{res} images but this scale needs {resolution}x{resolution}; "
            f"delete the folder or pass another --data"
        )
    layout = SplitLayout(root, n_views=m.n_views)
    done = [s for s in range(n_scenes) if is_scene_complete(layout, s)]
    if len(done) < n_scenes:
        return False, f"{len(done)}/{n_scenes} scenes complete"
    return True, "complete"


def _render_of(manifest: Manifest) -> tuple[int | None, bool | None, int | None]:
    """``(render samples, denoise, seed)`` a manifest records (None where it does not)."""
    render = manifest.extra.get("render")
    render = render if isinstance(render, dict) else {}
    samples, denoise, seed = render.get("samples"), render.get("denoise"), manifest.seed
    return (
        int(samples) if isinstance(samples, (int, float)) else None,
        bool(denoise) if isinstance(denoise, bool) else None,
        int(seed) if isinstance(seed, (int, float)) else None,
    )


def _nominal(settings: ScaleSettings, n: int, seed: int, source: str) -> dict[str, Any]:
    """What the scale asks of a split (render settings only for the generator)."""
    out: dict[str, Any] = {"n_scenes": n, "resolution": settings.resolution}
    if source == "generator":
        out.update(render_samples=settings.render_samples, denoise=settings.denoise, seed=seed)
    return out


def _deviations(nominal: dict[str, Any], actual: dict[str, Any]) -> tuple[str, ...]:
    """``"30 scenes (nominal 50)"``-style lines where a known actual value differs."""
    names = {
        "n_scenes": "scenes",
        "resolution": "px resolution",
        "render_samples": "render samples",
        "denoise": "denoise",
        "seed": "data seed",
    }
    out = []
    for k, label in names.items():
        want, got = nominal.get(k), actual.get(k)
        if want is not None and got is not None and want != got:
            out.append(f"{got} {label} (nominal {want})")
    return tuple(out)


def _own_scenes_complete(root: Path, manifest: Manifest) -> bool:
    """All scenes the split's own manifest announces are complete on disk."""
    n_own = manifest.n_scenes
    layout = SplitLayout(root, n_views=manifest.n_views)
    return n_own > 0 and all(is_scene_complete(layout, s) for s in range(n_own))


def source_of(manifest: Manifest) -> str:
    """The data source (:data:`DATA_SOURCES`) that made a split, from its manifest's
    ``generator`` field."""
    made_by = str(manifest.generator)
    return "synthetic" if made_by.startswith("svorf.synthetic") else "generator"


@dataclass(frozen=True)
class SplitState:
    """Whether a split folder can be used as it is on disk (:func:`split_state`).

    Attributes:
        usable: :func:`ensure_dataset` uses the folder without generating anything.
        why: ``"complete"``, ``"complete as found"``, or why not (``"no manifest.json"``,
            ``"3/5 scenes complete"``, ...).
        nominal: what the scale asks of the split: scene count and resolution, plus
            render samples, denoising and data seed for the generator.
    """

    usable: bool
    why: str
    nominal: dict[str, Any]


def split_state(
    data_root: str | os.PathLike,
    settings: ScaleSettings,
    preset: str,
    split: str,
    *,
    source: str,
    seed: int,
) -> SplitState:
    """Whether ``<data>/<scale>/<preset>/<split>`` is usable as found, as :func:`ensure_dataset`
    decides it before generating anything.

    Usable: the split holds the scale's scene count, every scene complete; or, for the
    ``generator`` source, it was made with other render settings or another seed (which
    the generator refuses to extend) and every scene its own manifest announces is
    complete (``"complete as found"``).

    Args:
        data_root: the ``--data`` folder.
        settings: the scale (scene count, resolution, render settings).
        preset, split: the split.
        source: the data source asking (``generator`` or ``synthetic``).
        seed: the generator's base seed.

    Raises:
        ValueError: the split holds another resolution than the scale's.
    """
    root = dataset_dir(data_root, settings.name, preset, split)
    n = settings.n_scenes(preset, split)
    ok, why = _complete(root, n, settings.resolution)
    nominal = _nominal(settings, n, seed, source)
    if not ok and source == "generator" and (root / "manifest.json").is_file():
        # An existing split the generator cannot extend (other render settings or seed:
        # it refuses to mix them) is used as found when its own scenes are complete.
        try:
            old = Manifest.from_json(read_json(root / "manifest.json"))
        except (OSError, ValueError):
            old = None  # unreadable: _complete said why
        if old is not None:
            samples, denoise, old_seed = _render_of(old)
            same = {"render_samples": samples, "denoise": denoise, "seed": old_seed}
            if _deviations(nominal, same) and _own_scenes_complete(root, old):
                ok, why = True, "complete as found"
    return SplitState(ok, why, nominal)


def _verify(root: Path) -> None:
    """``generators.verify.verify_split``; ValueError naming the first problems."""
    from generators.verify import verify_split

    problems = verify_split(root, max_problems=5)
    if problems:
        raise ValueError(
            f"{root}: the existing split fails generators.verify ({'; '.join(problems[:3])}); "
            f"delete the folder (the benchmark then generates it) or pass another --data"
        )


def _to_gray_inplace(root: Path, n_scenes: int, n_views: int) -> None:
    """Rec.601 luma as 3 equal channels (the ``clevr567-gray`` convention)."""
    layout = SplitLayout(root, n_views=n_views)
    for s in range(n_scenes):
        for v in range(n_views):
            rgb = read_rgb(layout.rgb(s, v)).astype(np.float64)
            y = rgb @ np.array(LUMA_REC601)
            y8 = np.clip(np.round(y), 0, 255).astype(np.uint8)
            write_rgb(layout.rgb(s, v), np.repeat(y8[..., None], 3, axis=2))


def _write_synthetic(root: Path, preset: str, split: str, n: int, res: int, seed: int) -> None:
    # clevr567-gray reuses the clevr567 test scenes (same seed), as the real preset does.
    base = "clevr567" if preset == "clevr567-gray" else preset
    offset = sum(ord(c) for c in base) * 10 + _SPLIT_SEED.get(split, 2)
    adapter.write_synthetic_split(
        root,
        n_scenes=n,
        resolution=res,
        seed=seed * 100_003 + offset,
        n_objects=_SYNTH_OBJECTS.get(preset, (2, 3)),
        preset=preset,
        split=split,
    )
    if preset == "clevr567-gray":
        _to_gray_inplace(root, n, 4)


def _run_generator(
    root: Path,
    preset: str,
    split: str,
    n: int,
    settings: ScaleSettings,
    seed: int,
    progress: bool,
    backend: str = "local",
    address: str | None = None,
) -> None:
    from benchmark import generator_bridge

    generator_bridge.generate(
        root,
        preset=preset,
        split=split,
        n_scenes=n,
        resolution=settings.resolution,
        samples=settings.render_samples,
        denoise=settings.denoise,
        seed=seed,
        progress=progress,
        backend=backend,
        address=address,
    )


def ensure_dataset(
    data_root: str | os.PathLike,
    settings: ScaleSettings,
    preset: str,
    split: str,
    *,
    source: str = "generator",
    seed: int = 0,
    progress: bool = True,
    backend: str = "local",
    address: str | None = None,
) -> DatasetInfo:
    """Return the split folder of ``preset``/``split`` at this scale, generating it if needed.

    Args:
        data_root: the ``--data`` folder.
        settings: the scale (scene counts, resolution, render samples).
        preset: generator preset name (``clevr567``, ``clevr567-heldout``, ...).
        split: ``train`` or ``test``.
        source: ``generator`` (Blender) or ``synthetic`` (analytic stand-in).
        seed: the generator's base seed.
        progress: show a progress bar while generating.
        backend, address: where the generator renders scenes (``local`` process pool or
            ``ray`` actors, see ``generators.ray_backend``); the bytes do not depend on it.

    Returns:
        The split's :class:`DatasetInfo` with its actual scene count, resolution and
        render settings (from its manifest) and their deviations from the scale's.

    Raises:
        ValueError: on an unknown source, a folder holding another resolution or made
            by another source, or a reused deviating split that fails verification.
    """
    if source not in DATA_SOURCES:
        raise ValueError(f"data source must be one of {DATA_SOURCES}, got {source!r}")
    root = dataset_dir(data_root, settings.name, preset, split)
    n = settings.n_scenes(preset, split)
    t0 = time.perf_counter()
    state = split_state(data_root, settings, preset, split, source=source, seed=seed)
    ok, nominal = state.usable, state.nominal
    generated = False
    if ok:
        found_manifest = Manifest.from_json(read_json(root / "manifest.json"))
        found = str(found_manifest.generator)
        actual = source_of(found_manifest)
        if actual != source:
            raise ValueError(
                f"{root} was made by {found!r} ({actual}) but --data-source is {source!r}; "
                f"delete the folder or pass another --data"
            )
    else:
        if source == "synthetic":
            _write_synthetic(root, preset, split, n, settings.resolution, seed)
        else:
            _run_generator(root, preset, split, n, settings, seed, progress, backend, address)
        generated = True
        ok, why = _complete(root, n, settings.resolution)
        if not ok:
            raise RuntimeError(f"{root}: still incomplete after generation ({why})")
    mf = Manifest.from_json(read_json(root / "manifest.json"))
    n_views, res = mf.n_views, mf.image_hw[0]
    samples, denoise, data_seed = _render_of(mf)
    n_found = len(SplitLayout(root, n_views=n_views).scene_indices())  # what svorf.data loads
    actual_settings = {
        "n_scenes": n_found,
        "resolution": res,
        "render_samples": samples,
        "denoise": denoise,
        "seed": data_seed,
    }
    deviations = _deviations(nominal, actual_settings)
    if deviations and not generated and source == "generator":
        _verify(root)
    return DatasetInfo(
        name=f"{preset}/{split}",
        preset=preset,
        split=split,
        path=root,
        fingerprint=adapter.dataset_fingerprint(root),
        n_scenes=n_found,
        n_views=n_views,
        resolution=res,
        source=source,
        generated_now=generated,
        wall_s=time.perf_counter() - t0,
        render_samples=samples,
        denoise=denoise,
        data_seed=data_seed,
        nominal=nominal,
        deviations=deviations,
    )
