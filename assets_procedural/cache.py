"""On-disk cache of procedural assets, keyed by (kind, id, generator version).

Where this sits: the scene sampler only stores ids; the Blender backend (or any
renderer) asks this module for a file path and imports the file. A chair is a
binary PLY (``chairs/chair_<version>_<id>.ply``), a texture a PNG
(``textures/texture_<version>_<id>_<size>.png``). Bumping
``CHAIR_GENERATOR_VERSION`` / ``TEXTURE_GENERATOR_VERSION`` changes the file
names, so stale files are never read.

Cache directory: the ``cache_dir`` argument, else the environment variable
``SVORF_ASSET_CACHE``, else ``~/.cache/svorf/assets``.

Safe under parallel workers (process pools, several machines on a shared file
system): each builder writes to its own unique temporary file in the target
directory and publishes it with ``os.replace`` (atomic on POSIX and Windows), so a
reader sees either no file or a complete one; concurrent builders of the same
asset produce identical bytes and the last rename wins.
"""

from __future__ import annotations

import io
import os
import re
from pathlib import Path

import trimesh

from assets_procedural.chairs import CHAIR_GENERATOR_VERSION, chair_mesh
from assets_procedural.ids import check_id
from assets_procedural.textures import TEXTURE_GENERATOR_VERSION, texture_image
from scenefmt import mkstemp_beside

ENV_VAR = "SVORF_ASSET_CACHE"
DEFAULT_CACHE_DIR = Path("~/.cache/svorf/assets")


def default_cache_dir() -> Path:
    """``$SVORF_ASSET_CACHE`` if set (and non-empty), else ``~/.cache/svorf/assets``."""
    env = os.environ.get(ENV_VAR, "").strip()
    return Path(env).expanduser() if env else DEFAULT_CACHE_DIR.expanduser()


def _resolve(cache_dir: str | os.PathLike | None) -> Path:
    return Path(cache_dir).expanduser() if cache_dir is not None else default_cache_dir()


def _safe(version: str) -> str:
    return re.sub(r"[^A-Za-z0-9.+-]", "_", version)


def atomic_write_bytes(path: Path, data: bytes) -> None:
    """Write ``data`` to ``path`` atomically (unique temp file in the same dir + rename)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = mkstemp_beside(path)  # mode 0o666 & ~umask, not mkstemp's 0600
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except FileNotFoundError:
            pass
        raise


def chair_cache_path(asset_id: int, cache_dir: str | os.PathLike | None = None) -> Path:
    """Where chair ``asset_id`` lives in the cache (the file may not exist yet)."""
    aid = check_id(asset_id, "asset_id")
    return _resolve(cache_dir) / "chairs" / f"chair_{_safe(CHAIR_GENERATOR_VERSION)}_{aid:06d}.ply"


def texture_cache_path(
    texture_id: int, size: int, cache_dir: str | os.PathLike | None = None
) -> Path:
    """Where texture ``texture_id`` at ``size`` lives in the cache (may not exist yet)."""
    tid = check_id(texture_id, "texture_id")
    name = f"texture_{_safe(TEXTURE_GENERATOR_VERSION)}_{tid:06d}_{int(size)}.png"
    return _resolve(cache_dir) / "textures" / name


def cached_chair_path(asset_id: int, cache_dir: str | os.PathLike | None = None) -> Path:
    """Path of chair ``asset_id`` as a binary PLY, building and writing it once.

    The PLY holds float64 vertices and triangle faces exactly as
    ``chair_mesh(asset_id)`` builds them (canonical frame: see
    ``assets_procedural.chairs``). Read it back with :func:`load_cached_chair` or
    ``trimesh.load(path, process=False)``.
    """
    path = chair_cache_path(asset_id, cache_dir)
    if not path.is_file():
        mesh = chair_mesh(asset_id)
        data = mesh.export(file_type="ply", encoding="binary")
        atomic_write_bytes(path, data)
    return path


def load_cached_chair(asset_id: int, cache_dir: str | os.PathLike | None = None) -> trimesh.Trimesh:
    """Load chair ``asset_id`` from the cache (building it first if needed)."""
    mesh = trimesh.load(cached_chair_path(asset_id, cache_dir), file_type="ply", process=False)
    if not isinstance(mesh, trimesh.Trimesh):
        raise TypeError(f"cached chair {asset_id} did not load as a single mesh")
    return mesh


def cached_texture_path(
    texture_id: int, size: int = 256, cache_dir: str | os.PathLike | None = None
) -> Path:
    """Path of ``texture_image(texture_id, size)`` as an 8-bit RGB PNG, written once."""
    path = texture_cache_path(texture_id, size, cache_dir)
    if not path.is_file():
        from PIL import Image

        img = texture_image(texture_id, size)  # validates id and size
        buf = io.BytesIO()
        Image.fromarray(img).save(buf, format="PNG")
        atomic_write_bytes(path, buf.getvalue())
    return path
