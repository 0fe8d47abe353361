"""Atomic writers and readers for every file type of the dataset contract."""

from __future__ import annotations

import io
import json
import os
import tempfile
import threading
from pathlib import Path
from typing import Any

import numpy as np
from PIL import Image

_FILE_MODE: int | None = None
_FILE_MODE_LOCK = threading.Lock()


def _read_umask() -> int:
    # Linux reports the umask without changing it (race-free, kernel >= 4.7).
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith("Umask:"):
                    return int(line.split()[1], 8)
    except (OSError, ValueError, IndexError):
        pass
    # Elsewhere the only way to read it is to set it and put it back. The umask is
    # process-wide: a file another thread creates between these two calls gets umask 0,
    # so this runs at most once per process (under the lock) and the result is cached.
    old = os.umask(0)
    os.umask(old)
    return old


def default_file_mode() -> int:
    """The mode a plain ``open(path, "w")`` gives a new file: ``0o666 & ~umask``.

    ``tempfile.mkstemp`` creates files with mode 0600 whatever the umask, so every
    temp-file-then-rename writer must chmod its temp file to this (use
    :func:`mkstemp_beside`, which does). The umask is read once, at the first call, and
    cached; after changing the umask in-process call :func:`reset_file_mode_cache`.
    """
    global _FILE_MODE
    with _FILE_MODE_LOCK:
        if _FILE_MODE is None:
            _FILE_MODE = 0o666 & ~_read_umask()
        return _FILE_MODE


def reset_file_mode_cache() -> None:
    """Forget the cached umask (the next :func:`default_file_mode` reads it again)."""
    global _FILE_MODE
    with _FILE_MODE_LOCK:
        _FILE_MODE = None


def mkstemp_beside(path: str | os.PathLike, suffix: str = ".tmp") -> tuple[int, Path]:
    """A new hidden temp file in ``path``'s folder, for an atomic write of ``path``.

    Like ``tempfile.mkstemp`` (returns ``(fd, temp path)``; the caller closes the fd and
    ``os.replace``-s the temp file onto ``path``), but the file has
    :func:`default_file_mode` instead of 0600, so the renamed file gets the mode a plain
    ``open()`` would have given it.
    """
    path = Path(path)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=suffix, dir=path.parent)
    try:
        os.fchmod(fd, default_file_mode())
    except BaseException:
        os.close(fd)
        os.unlink(tmp)
        raise
    return fd, Path(tmp)


def _tmp_path(path: Path, suffix: str = ".tmp") -> Path:
    fd, tmp = mkstemp_beside(path, suffix)
    os.close(fd)
    return tmp


def atomic_write_bytes(path: str | os.PathLike, data: bytes) -> None:
    """Write ``data`` to a temp file beside ``path`` and rename it into place."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = _tmp_path(path)
    try:
        with open(tmp, "wb") as f:
            f.write(data)
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def atomic_write_json(path: str | os.PathLike, obj: Any) -> None:
    """Atomic JSON write (sorted keys, 2-space indent, trailing newline)."""
    text = json.dumps(obj, indent=2, sort_keys=True) + "\n"
    atomic_write_bytes(path, text.encode())


def read_json(path: str | os.PathLike) -> Any:
    with open(path) as f:
        return json.load(f)


def _png_bytes(arr: np.ndarray, mode: str) -> bytes:
    buf = io.BytesIO()
    im = Image.fromarray(arr)  # uint8 [H,W] -> "L", uint8 [H,W,3] -> "RGB"
    if im.mode != mode:
        raise ValueError(f"expected a {mode} image, got {im.mode}")
    im.save(buf, format="PNG", compress_level=6)
    return buf.getvalue()


def write_rgb(path: str | os.PathLike, rgb: np.ndarray) -> None:
    """RGB uint8 [H, W, 3] (sRGB) as PNG."""
    rgb = np.asarray(rgb)
    if rgb.dtype != np.uint8 or rgb.ndim != 3 or rgb.shape[2] != 3:
        raise ValueError(f"rgb must be uint8 [H, W, 3], got {rgb.dtype} {rgb.shape}")
    atomic_write_bytes(path, _png_bytes(np.ascontiguousarray(rgb), "RGB"))


def read_rgb(path: str | os.PathLike) -> np.ndarray:
    """uint8 [H, W, 3]."""
    with Image.open(path) as im:
        return np.asarray(im.convert("RGB"))


def write_mask(path: str | os.PathLike, mask: np.ndarray) -> None:
    """uORF grey mask uint8 [H, W] (see ``layout.uorf_mask_from_instances``)."""
    mask = np.asarray(mask)
    if mask.dtype != np.uint8 or mask.ndim != 2:
        raise ValueError(f"mask must be uint8 [H, W], got {mask.dtype} {mask.shape}")
    atomic_write_bytes(path, _png_bytes(mask, "L"))


def write_instances(path: str | os.PathLike, ids: np.ndarray) -> None:
    """Instance ids uint8 [H, W], 0 = background, as a lossless 8-bit PNG."""
    ids = np.asarray(ids)
    if ids.dtype != np.uint8 or ids.ndim != 2:
        raise ValueError(f"instance ids must be uint8 [H, W], got {ids.dtype} {ids.shape}")
    atomic_write_bytes(path, _png_bytes(ids, "L"))


def read_instances(path: str | os.PathLike) -> np.ndarray:
    """uint8 [H, W] (also reads a ``_mask.png`` as raw grey levels)."""
    with Image.open(path) as im:
        if im.mode != "L":
            raise ValueError(f"{path}: expected an 8-bit grey PNG, got mode {im.mode}")
        return np.asarray(im)


def _oiio():
    try:
        import OpenImageIO as oiio
    except ImportError as e:  # pragma: no cover - install problem
        raise ImportError(
            "OpenImageIO is needed for depth EXRs: pip install 'openimageio>=3.0,<3.1'"
        ) from e
    return oiio


def write_depth_exr(path: str | os.PathLike, depth_z: np.ndarray) -> None:
    """Planar depth float32 [H, W] (camera z, world units; background = inf) as EXR.

    Written losslessly (ZIP compression, FLOAT pixels), atomically.
    """
    depth_z = np.ascontiguousarray(depth_z, dtype=np.float32)
    if depth_z.ndim != 2:
        raise ValueError(f"depth must be [H, W], got shape {depth_z.shape}")
    oiio = _oiio()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = _tmp_path(path, suffix=".tmp.exr")  # OIIO picks the format from the suffix
    h, w = depth_z.shape
    spec = oiio.ImageSpec(w, h, 1, "float")
    spec.channelnames = ("Z",)
    spec.attribute("compression", "zip")
    # A fixed header so identical depth maps give identical bytes (OIIO stamps the
    # wall-clock time otherwise): determinism is checked byte for byte.
    spec.attribute("DateTime", "1970:01:01 00:00:00")
    spec.attribute("Software", "scenefmt")
    out = oiio.ImageOutput.create(str(tmp))
    if out is None:
        raise OSError(f"OpenImageIO cannot create {tmp}: {oiio.geterror()}")
    try:
        if not out.open(str(tmp), spec):
            raise OSError(f"OpenImageIO cannot open {tmp}: {out.geterror()}")
        if not out.write_image(depth_z[:, :, None]):
            raise OSError(f"OpenImageIO cannot write {tmp}: {out.geterror()}")
        out.close()
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def read_depth_exr(path: str | os.PathLike) -> np.ndarray:
    """float32 [H, W] planar depth from a single-channel EXR."""
    oiio = _oiio()
    inp = oiio.ImageInput.open(str(path))
    if inp is None:
        raise OSError(f"cannot open depth EXR {path}: {oiio.geterror()}")
    try:
        arr = inp.read_image(format="float")
    finally:
        inp.close()
    if arr is None:
        raise OSError(f"cannot read depth EXR {path}")
    arr = np.asarray(arr, dtype=np.float32)
    return arr[..., 0] if arr.ndim == 3 else arr


def write_matrix_txt(path: str | os.PathLike, mat: np.ndarray) -> None:
    """A matrix as text (``np.loadtxt`` reads it back; uORF's ``_RT.txt`` format)."""
    buf = io.StringIO()
    np.savetxt(buf, np.asarray(mat, dtype=np.float64), fmt="%.10f")
    atomic_write_bytes(path, buf.getvalue().encode())


def read_matrix_txt(path: str | os.PathLike) -> np.ndarray:
    return np.loadtxt(path, dtype=np.float64)


def write_movement_txt(path: str | os.PathLike, dx: float, dy: float) -> None:
    """uORF's ``{scene:03d}_movement.txt``: x then y (world units), one per line."""
    for name, v in (("dx", dx), ("dy", dy)):
        if not np.isfinite(v):
            raise ValueError(f"{name} must be finite, got {v}")
    atomic_write_bytes(path, f"{float(dx):.10f}\n{float(dy):.10f}\n".encode())


def read_movement_txt(path: str | os.PathLike) -> tuple[float, float]:
    """``(dx, dy)`` of a movement file, read line by line as uORF's loader does."""
    with open(path) as f:
        return float(f.readline()), float(f.readline())
