"""The one place where the benchmark calls the dataset generator (``generators``).

Where this sits: :func:`benchmark.datasets.ensure_dataset` calls :func:`generate` when a
split folder is missing or incomplete; it fills the generator's own config,
``generators.pipeline.GenerateConfig``, from the benchmark's scale settings and calls
``generators.pipeline.generate_dataset``. Nothing else in the benchmark imports the
generator.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

__all__ = ["DatasetUnavailable", "entry_point", "generate", "known_presets"]


class DatasetUnavailable(RuntimeError):
    """The generator cannot make this dataset here (no bpy, unknown preset...); one line."""


def entry_point() -> tuple[type, Any]:
    """``(GenerateConfig, generate_dataset)`` of ``generators.pipeline``.

    Raises:
        DatasetUnavailable: if the generator package cannot be imported here.
    """
    try:
        from generators.pipeline import GenerateConfig, generate_dataset
    except ImportError as err:
        raise DatasetUnavailable(
            f"the generator cannot be imported ({err}); use --data-source synthetic for a stand-in"
        ) from err
    return GenerateConfig, generate_dataset


def known_presets() -> list[str]:
    """Preset names registered in ``generators.presets`` (empty if it cannot be imported)."""
    try:
        from generators.presets import PRESETS
    except ImportError:
        return []
    return sorted(PRESETS)


def generate(
    root: str | os.PathLike,
    *,
    preset: str,
    split: str,
    n_scenes: int,
    resolution: int,
    samples: int | None,
    denoise: bool | None,
    seed: int,
    progress: bool = True,
    workers: int | None = None,
    backend: str = "local",
    address: str | None = None,
) -> None:
    """Render ``n_scenes`` scenes of ``preset``/``split`` into ``root`` (resuming).

    ``samples``, ``denoise`` and ``workers`` left None keep the generator's defaults.

    Raises:
        DatasetUnavailable: if the preset is unknown or the generator cannot run.
    """
    presets = known_presets()
    if presets and preset not in presets:
        raise DatasetUnavailable(
            f"generator preset {preset!r} is not registered (known: {', '.join(presets)})"
        )
    config_cls, generate_dataset = entry_point()
    optional = {"samples": samples, "denoise": denoise, "workers": workers}
    if backend != "local" or address is not None:
        optional.update(backend=backend, address=address)
    cfg = config_cls(
        preset=preset,
        split=split,
        n=int(n_scenes),
        out=Path(root),
        resolution=int(resolution),
        seed=int(seed),
        progress=bool(progress),
        **{k: v for k, v in optional.items() if v is not None},
    )
    try:
        generate_dataset(cfg)
    except ImportError as err:  # bpy missing
        raise DatasetUnavailable(f"the Blender generator cannot run here ({err})") from err
