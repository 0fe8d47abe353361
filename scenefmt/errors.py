"""``DatasetError`` and the one-line messages of a split folder that cannot be read.

Where this sits: in the format layer, below the two split readers, ``svorf.data`` (our
layout) and :mod:`scenefmt.uorf` (the uORF layout). Both read every file through
:func:`read_file` and report a missing one with :func:`missing_file`, so each failure is
one :class:`DatasetError` line that names the file and the fix. ``svorf.data`` re-exports
:class:`DatasetError`.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

__all__ = ["DatasetError", "missing_file", "read_file"]


class DatasetError(ValueError):
    """A split folder that cannot be read; the message is one line naming the fix."""


def missing_file(path: Path, root: Path) -> DatasetError:
    """The error for ``path``, a file the split folder ``root`` should hold but does not."""
    return DatasetError(
        f"{path}: missing - {root} is not a complete split folder (run `generate verify {root}`)"
    )


def read_file(reader: Callable[[Path], Any], path: Path, root: Path) -> Any:
    """``reader(path)`` with any decoding failure turned into a one-line DatasetError.

    Args:
        reader: e.g. ``scenefmt.read_rgb`` or ``numpy.load``.
        path: the file, inside the split folder ``root`` (named in the fix).

    Raises:
        DatasetError: the file is missing (:func:`missing_file`) or cannot be decoded.
    """
    try:
        return reader(path)
    except FileNotFoundError as e:
        raise missing_file(path, root) from e
    except (OSError, ValueError, SyntaxError) as e:
        msg = (str(e).strip().splitlines() or [type(e).__name__])[0]
        raise DatasetError(
            f"{path}: unreadable ({msg[:120]}); run `generate verify {root}` "
            f"and regenerate the scene"
        ) from e
