"""Report plumbing: environment facts, atomic JSON, per-row result files.

Where this sits: protocols (``benchmark.protocols``) collect rows and call
:func:`write_report`, which validates the dict against :mod:`benchmark.schema`
before anything is written. Row result files (:class:`RowStore`) make a protocol
resumable: a finished row is a JSON file written atomically, and a rerun skips it.
"""

from __future__ import annotations

import datetime as _dt
import hashlib
import json
import os
import platform
import re
from pathlib import Path
from typing import Any

from benchmark.schema import METRIC_UNITS, REPORT_KIND, REPORT_SCHEMA_VERSION, validate_report
from scenefmt import atomic_write_bytes

__all__ = [
    "RowStore",
    "dumps",
    "git_info",
    "hardware_info",
    "new_report",
    "stable_hash",
    "utc_now",
    "write_json",
    "write_report",
]


def utc_now() -> str:
    """Current UTC time as ``YYYY-MM-DDTHH:MM:SSZ``."""
    return _dt.datetime.now(_dt.UTC).strftime("%Y-%m-%dT%H:%M:%SZ")


def dumps(obj: Any) -> str:
    """Strict JSON text (``allow_nan=False``: NaN/inf raise instead of writing invalid JSON)."""
    return json.dumps(obj, indent=2, sort_keys=True, allow_nan=False) + "\n"


def write_json(path: str | os.PathLike, obj: Any) -> None:
    """Write strict JSON atomically (temp file + rename)."""
    atomic_write_bytes(path, dumps(obj).encode())


def stable_hash(obj: Any, n: int = 16) -> str:
    """First ``n`` hex digits of the SHA-256 of the canonical JSON of ``obj``."""
    text = json.dumps(obj, sort_keys=True, separators=(",", ":"), allow_nan=False, default=str)
    return hashlib.sha256(text.encode()).hexdigest()[:n]


def _find_git_dir(start: Path) -> Path | None:
    for d in [start, *start.parents]:
        g = d / ".git"
        if g.is_dir():
            return g
        if g.is_file():  # worktree / submodule: "gitdir: <path>"
            text = g.read_text().strip()
            if text.startswith("gitdir:"):
                p = Path(text.split(":", 1)[1].strip())
                return p if p.is_absolute() else (d / p).resolve()
    return None


def git_info(start: str | os.PathLike | None = None) -> dict[str, Any]:
    """The checked-out commit, read from ``.git`` files (no ``git`` process is run).

    Args:
        start: Folder to search upwards from (default: this package's folder).

    Returns:
        ``{"commit": 40-hex str | None, "dirty": None, "reason": str | None}``.
        ``dirty`` is not determined (that needs the index and a ``git`` binary).
    """
    start = Path(start) if start else Path(__file__).resolve().parent
    gdir = _find_git_dir(start.resolve())
    if gdir is None:
        return {"commit": None, "dirty": None, "reason": "no .git folder above " + str(start)}
    try:
        head = (gdir / "HEAD").read_text().strip()
        if head.startswith("ref:"):
            ref = head.split(":", 1)[1].strip()
            common = gdir
            if (gdir / "commondir").is_file():
                common = (gdir / (gdir / "commondir").read_text().strip()).resolve()
            for base in (gdir, common):
                if (base / ref).is_file():
                    commit = (base / ref).read_text().strip()
                    break
            else:
                commit = None
                packed = common / "packed-refs"
                if packed.is_file():
                    for line in packed.read_text().splitlines():
                        parts = line.split()
                        if len(parts) == 2 and parts[1] == ref:
                            commit = parts[0]
                if commit is None:
                    return {"commit": None, "dirty": None, "reason": f"{ref} has no commit yet"}
        else:
            commit = head
    except OSError as err:
        return {"commit": None, "dirty": None, "reason": f"cannot read {gdir}: {err}"}
    if not re.fullmatch(r"[0-9a-f]{40}", commit or ""):
        return {"commit": None, "dirty": None, "reason": f"unexpected HEAD content {commit!r}"}
    return {"commit": commit, "dirty": None, "reason": "dirty state not checked (no git process)"}


def _cpu_model() -> str:
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine() or "unknown"


def hardware_info(device: str) -> dict[str, Any]:
    """CPU model, core count, torch version and the compute device of this run."""
    import torch

    gpu = None
    if device.startswith("cuda") and torch.cuda.is_available():
        gpu = torch.cuda.get_device_name(torch.device(device))
    try:
        cores = len(os.sched_getaffinity(0))
    except AttributeError:  # pragma: no cover - non-Linux
        cores = os.cpu_count() or 1
    return {
        "cpu_model": _cpu_model(),
        "cpu_cores": int(cores),
        "torch_threads": int(torch.get_num_threads()),
        "torch_version": torch.__version__,
        "device": device,
        "gpu_name": gpu,
        "python_version": platform.python_version(),
        "platform": platform.platform(),
    }


def new_report(protocol: str, scale: str, device: str) -> dict[str, Any]:
    """A report skeleton with the environment filled in and empty row lists."""
    return {
        "schema_version": REPORT_SCHEMA_VERSION,
        "kind": REPORT_KIND,
        "protocol": protocol,
        "scale": scale,
        "status": "complete",
        "created_utc": utc_now(),
        "git": git_info(),
        "hardware": hardware_info(device),
        "seeds": {"data": 0, "train": 0, "eval": 0},
        "scale_settings": {},
        "datasets": [],
        "models": [],
        "wall_time_s": {"data": 0.0, "training": 0.0, "evaluation": 0.0, "total": 0.0},
        "rows": [],
        "verdicts": [],
        "notes": [],
        "figures": [],
        "units": dict(METRIC_UNITS),
    }


def write_report(path: str | os.PathLike, report: dict[str, Any]) -> None:
    """Validate ``report`` against the schema, then write it atomically.

    Raises:
        benchmark.schema.SchemaError: If the report is invalid (nothing is written).
    """
    validate_report(report)
    write_json(path, report)


class RowStore:
    """Finished rows of one protocol run, one JSON file each (the resume mechanism).

    Args:
        root: Folder of the row files (``<report dir>/rows``).
        context: Everything a row's value depends on beyond its own id (scale,
            dataset fingerprints...). Stored in each file; a file whose context
            differs is treated as missing, so a changed setup is recomputed.
    """

    def __init__(self, root: str | os.PathLike, context: dict[str, Any]) -> None:
        self.root = Path(root)
        self.context_hash = stable_hash(context)

    def _path(self, row_id: str) -> Path:
        safe = re.sub(r"[^A-Za-z0-9_.-]+", "_", row_id)
        return self.root / f"{safe}.json"

    def get(self, row_id: str) -> dict[str, Any] | None:
        """The stored row, or None if absent, unreadable or from another context."""
        p = self._path(row_id)
        try:
            data = json.loads(p.read_text())
        except (OSError, ValueError):
            return None
        if data.get("context") != self.context_hash or data.get("row", {}).get("id") != row_id:
            return None
        return data["row"]

    def put(self, row: dict[str, Any]) -> None:
        """Store a finished row atomically."""
        write_json(self._path(row["id"]), {"context": self.context_hash, "row": row})
