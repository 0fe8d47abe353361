"""The one place where the benchmark calls the dataset generator (``generators``).

Where this sits: :func:`benchmark.datasets.ensure_dataset` calls :func:`generate`
when a split folder is missing or incomplete. The generator's importable entry
point is ``generate_dataset(cfg)`` (a thin CLI wraps it, STYLE principle 6);
its config dataclass is filled here from the benchmark's scale settings. Only
the fields the generator's config actually has are set, so additive changes on
the generator side need no change here.
"""

from __future__ import annotations

import dataclasses
import importlib
import inspect
import os
from pathlib import Path
from typing import Any

__all__ = ["DatasetUnavailable", "generate", "known_presets"]

# Modules searched, in order, for ``generate_dataset``.
_MODULES = ("generators.pipeline", "generators.dataset", "generators.generate", "generators")


class DatasetUnavailable(RuntimeError):
    """The generator cannot make this dataset here (no bpy, unknown preset...); one line."""


def _entry_point():
    errors = []
    for name in _MODULES:
        try:
            mod = importlib.import_module(name)
            fn = getattr(mod, "generate_dataset", None)
        except ImportError as err:  # also a lazy package attribute that fails to import
            errors.append(f"{name}: {err}")
            continue
        if callable(fn):
            return mod, fn
    raise DatasetUnavailable(
        "the generator has no importable generate_dataset(cfg) ("
        + "; ".join(errors or [f"searched {', '.join(_MODULES)}"])
        + "); use --data-source synthetic for a stand-in"
    )


def known_presets() -> list[str]:
    """Preset names registered in ``generators.presets`` (empty if it cannot be imported)."""
    try:
        from generators.presets import PRESETS
    except ImportError:
        return []
    return sorted(PRESETS)


def _config_class(mod: Any, fn: Any) -> Any:
    hints = inspect.signature(fn).parameters
    if hints:
        ann = next(iter(hints.values())).annotation
        if isinstance(ann, str):
            ann = getattr(mod, ann, None) or getattr(
                importlib.import_module(mod.__name__), ann, None
            )
        if dataclasses.is_dataclass(ann):
            return ann
    for name in ("GenerateConfig", "GenerationConfig", "DatasetConfig", "GeneratorConfig"):
        cls = getattr(mod, name, None)
        if cls is not None and dataclasses.is_dataclass(cls):
            return cls
    raise DatasetUnavailable(f"cannot find the config dataclass of {mod.__name__}.generate_dataset")


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

    Raises:
        DatasetUnavailable: if the preset is unknown or the generator cannot run.
    """
    presets = known_presets()
    if presets and preset not in presets:
        raise DatasetUnavailable(
            f"generator preset {preset!r} is not registered (known: {', '.join(presets)})"
        )
    mod, fn = _entry_point()
    cls = _config_class(mod, fn)
    fields = {f.name for f in dataclasses.fields(cls)}
    values: dict[str, Any] = {}

    def put(names: tuple[str, ...], value: Any) -> None:
        for n in names:
            if n in fields:
                values[n] = value
                return

    put(("preset",), preset)
    put(("split",), split)
    put(("n", "n_scenes", "count"), int(n_scenes))
    put(("out", "out_dir", "output", "root", "path"), Path(root))
    put(("resolution",), int(resolution))
    put(("seed",), int(seed))
    put(("progress",), bool(progress))
    if samples is not None:
        put(("samples", "spp"), int(samples))
    if denoise is not None:
        put(("denoise",), bool(denoise))
    if workers is not None:
        put(("workers",), int(workers))
    if backend != "local" or address is not None:
        if "backend" not in fields:
            raise DatasetUnavailable(
                f"this generator has no backend option, so it cannot render with {backend!r}"
            )
        put(("backend",), backend)
        put(("address",), address)
    missing = [
        f.name
        for f in dataclasses.fields(cls)
        if f.default is dataclasses.MISSING
        and f.default_factory is dataclasses.MISSING  # type: ignore[misc]
        and f.name not in values
    ]
    if missing:
        raise DatasetUnavailable(
            f"{cls.__name__} needs fields the benchmark does not set: {missing}"
        )
    try:
        fn(cls(**values))
    except ImportError as err:  # bpy missing
        raise DatasetUnavailable(f"the Blender generator cannot run here ({err})") from err
