"""One-line progress messages of the benchmark, on stderr.

Where this sits: every benchmark module that reports progress (the protocol engine
:mod:`benchmark.runner`, its Ray jobs :mod:`benchmark.ray_jobs`, the protocols) calls
:func:`log`, so that every line starts with the same ``[benchmark]`` tag and stdout stays
free for what ``benchmark`` prints as its result (the report paths).
"""

from __future__ import annotations

import sys

__all__ = ["log"]


def log(msg: str) -> None:
    """Print ``[benchmark] msg`` to stderr (flushed at once)."""
    print(f"[benchmark] {msg}", file=sys.stderr, flush=True)
