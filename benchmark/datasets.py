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

The fingerprint (SHA-256 over ``manifest.json`` and the scene JSONs, via the
adapter) goes into the model cache key and into the report.
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from benchmark import adapter
from benchmark.scales import ScaleSettings
from scenefmt import SplitLayout, is_scene_complete, read_json, read_rgb, write_rgb

__all__ = ["DATA_SOURCES", "DatasetInfo", "dataset_dir", "ensure_dataset"]

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
        }


def dataset_dir(data_root: str | os.PathLike, scale: str, preset: str, split: str) -> Path:
    """``<data>/<scale>/<preset>/<split>``."""
    return Path(data_root) / scale / preset / split


def _complete(root: Path, n_scenes: int, resolution: int) -> tuple[bool, str]:
    """Whether ``root`` holds ``n_scenes`` complete scenes at ``resolution``."""
    manifest = root / "manifest.json"
    if not manifest.is_file():
        return False, "no manifest.json"
    try:
        m = read_json(manifest)
    except (OSError, ValueError) as err:
        return False, f"unreadable manifest ({err})"
    res = m.get("resolution")
    res = res[0] if isinstance(res, list) else res
    if res is not None and int(res) != resolution:
        raise ValueError(
            f"{root}: holds {res}x{res} images but this scale needs {resolution}x{resolution}; "
            f"delete the folder or pass another --data"
        )
    layout = SplitLayout(root, n_views=int(m.get("n_views", 4)))
    done = [s for s in range(n_scenes) if is_scene_complete(layout, s)]
    if len(done) < n_scenes:
        return False, f"{len(done)}/{n_scenes} scenes complete"
    return True, "complete"


def _to_gray_inplace(root: Path, n_scenes: int, n_views: int) -> None:
    """Rec.601 luma as 3 equal channels (the ``clevr567-gray`` convention)."""
    layout = SplitLayout(root, n_views=n_views)
    for s in range(n_scenes):
        for v in range(n_views):
            rgb = read_rgb(layout.rgb(s, v)).astype(np.float64)
            y = 0.299 * rgb[..., 0] + 0.587 * rgb[..., 1] + 0.114 * rgb[..., 2]
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
    root: Path, preset: str, split: str, n: int, settings: ScaleSettings, seed: int, progress: bool
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

    Raises:
        ValueError: on an unknown source, or a folder holding another resolution.
    """
    if source not in DATA_SOURCES:
        raise ValueError(f"data source must be one of {DATA_SOURCES}, got {source!r}")
    root = dataset_dir(data_root, settings.name, preset, split)
    n = settings.n_scenes(preset, split)
    t0 = time.perf_counter()
    ok, why = _complete(root, n, settings.resolution)
    generated = False
    if ok:
        manifest = read_json(root / "manifest.json")
        found = str(manifest.get("generator", ""))
        actual = "synthetic" if found.startswith("svorf.synthetic") else "generator"
        if actual != source:
            raise ValueError(
                f"{root} was made by {found!r} ({actual}) but --data-source is {source!r}; "
                f"delete the folder or pass another --data"
            )
    else:
        if source == "synthetic":
            _write_synthetic(root, preset, split, n, settings.resolution, seed)
        else:
            _run_generator(root, preset, split, n, settings, seed, progress)
        generated = True
        ok, why = _complete(root, n, settings.resolution)
        if not ok:
            raise RuntimeError(f"{root}: still incomplete after generation ({why})")
    manifest = read_json(root / "manifest.json")
    return DatasetInfo(
        name=f"{preset}/{split}",
        preset=preset,
        split=split,
        path=root,
        fingerprint=adapter.dataset_fingerprint(root),
        n_scenes=n,
        n_views=int(manifest.get("n_views", 4)),
        resolution=settings.resolution,
        source=source,
        generated_now=generated,
        wall_s=time.perf_counter() - t0,
    )
