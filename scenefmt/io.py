"""Atomic writers and readers for every file type of the dataset contract."""

from __future__ import annotations

import io
import json
import os
import tempfile
from pathlib import Path
from typing import Any

import numpy as np
from PIL import Image


def _tmp_path(path: Path, suffix: str = ".tmp") -> Path:
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=suffix, dir=path.parent)
    os.close(fd)
    return Path(tmp)


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
