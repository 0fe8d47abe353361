"""Small command-line helpers shared by the ``generate``, ``svorf`` and ``benchmark`` commands.

They live here because ``scenefmt`` is the one base package that all three already import
(``generators`` imports neither ``svorf`` nor ``benchmark``, and ``svorf`` does not import
``benchmark``); nothing in this module is about the file format. Standard library only.

The rule every command follows: an error is **one line** on stderr,
``PROG: error: what was wrong; how to fix it``, with exit status :data:`USAGE` (2) for a
bad command line and :data:`RUNTIME` (1) for a failure while running.

- :func:`choose` checks a name against the names it may be (presets, scales, protocols,
  datasets) and says "did you mean ...?" for a near miss;
- :class:`OneLineParser` is an ``argparse`` parser whose errors are one line (with the
  same "did you mean" for ``choices=``) and whose ``--help`` shows each option's default;
- :func:`error_line` turns an exception into that one line's message;
- :func:`doc_summary` is a module docstring's first paragraph, for ``description=``;
- :func:`progress_kwargs` paces a progress bar by where it is written (a terminal or a log).
"""

from __future__ import annotations

import argparse
import difflib
import functools
import sys
from collections.abc import Iterable
from typing import Any, NoReturn

__all__ = [
    "RUNTIME",
    "USAGE",
    "DefaultsFormatter",
    "OneLineParser",
    "choose",
    "did_you_mean",
    "doc_summary",
    "error_line",
    "fail",
    "progress_kwargs",
    "unknown_choice",
]

#: Seconds between progress-bar lines when stderr is a file or a pipe (nohup, CI logs).
LOG_PROGRESS_INTERVAL_S = 30.0

#: Exit status of a bad command line (argparse's).
USAGE = 2
#: Exit status of a failure while running.
RUNTIME = 1


def did_you_mean(name: object, options: Iterable[object]) -> str:
    """``"; did you mean 'x'?"`` for the closest of ``options`` to ``name``, else ``""``."""
    names = [str(o) for o in options]
    close = difflib.get_close_matches(str(name), names, n=1, cutoff=0.6)
    return f"; did you mean {close[0]!r}?" if close else ""


def unknown_choice(name: object, options: Iterable[object], what: str) -> str:
    """The one-line message for ``name`` not being one of ``options``:
    ``unknown scale 'smok'; did you mean 'smoke'? (choose from smoke, cpu, paper)``."""
    names = [str(o) for o in options]
    return (
        f"unknown {what} {str(name)!r}{did_you_mean(name, names)} (choose from {', '.join(names)})"
    )


def choose(name: str, options: Iterable[str], what: str) -> str:
    """``name`` if it is one of ``options``; otherwise ValueError with :func:`unknown_choice`.

    Args:
        name: the name given (a preset, scale, protocol, dataset ...).
        options: the names it may be, in the order to list them.
        what: what a name is, for the message ("scale", "preset", ...).
    """
    names = list(options)
    if name not in names:
        raise ValueError(unknown_choice(name, names, what))
    return name


def error_line(err: BaseException) -> str:
    """One line saying what went wrong: the first line of the message; a file error as
    ``PATH: no such file or directory`` rather than ``[Errno 2] ...``."""
    if isinstance(err, OSError) and err.strerror:
        where = err.filename if err.filename is not None else ""
        return f"{where}: {err.strerror.lower()}" if where else err.strerror.lower()
    text = str(err).strip()
    return text.splitlines()[0] if text else type(err).__name__


def doc_summary(doc: str | None) -> str:
    """The first paragraph of a docstring as one line (a whole sentence, never its first
    physical line only), for an ``argparse`` description."""
    para = (doc or "").strip().split("\n\n")[0]
    return " ".join(para.replace("``", "").split())


def fail(prog: str, message: str, status: int = USAGE) -> int:
    """Print ``PROG: error: MESSAGE`` (one line) to stderr and return ``status``."""
    print(f"{prog}: error: {message}", file=sys.stderr)
    return status


class DefaultsFormatter(argparse.HelpFormatter):
    """Help that ends each option's text with ``(default: X)``, unless the text already
    speaks of a default or there is none to show (None, False, empty, suppressed)."""

    def _get_help_string(self, action: argparse.Action) -> str | None:
        text = action.help
        if not text or "default" in text.lower() or "%(default)" in text:
            return text
        default = action.default
        if default is None or default is False or default is argparse.SUPPRESS:
            return text
        if isinstance(default, (list, tuple)) and not default:  # action="append" etc.
            return text
        if action.nargs == 0:  # a flag (--x, --no-x, --x/--no-x): its help says the default
            return text
        if not action.option_strings and action.nargs not in (
            argparse.OPTIONAL,
            argparse.ZERO_OR_MORE,
        ):
            return text  # a required positional has no default to show
        return f"{text} (default: %(default)s)"


class OneLineParser(argparse.ArgumentParser):
    """``argparse`` with one-line errors and defaults in ``--help``.

    An error prints ``TOOL: error: MESSAGE (see `PROG --help`)`` and exits with status 2;
    TOOL is the top-level command (``tool``, default ``prog``), also in a subcommand's
    parser, so that usage errors read like the command's other errors (``svorf: error:
    ...``, not ``svorf: error: svorf train: ...``). A value outside ``choices=`` is reported
    with :func:`unknown_choice`, so a near miss gets "did you mean ...?". Subparsers made
    through ``add_subparsers`` are of this class too.
    """

    def __init__(self, *args: Any, tool: str | None = None, **kwargs: Any) -> None:
        kwargs.setdefault("formatter_class", DefaultsFormatter)
        super().__init__(*args, **kwargs)
        #: The name errors are printed under.
        self.tool = tool or self.prog

    def add_subparsers(self, **kwargs: Any) -> Any:
        kwargs.setdefault("parser_class", functools.partial(type(self), tool=self.tool))
        return super().add_subparsers(**kwargs)

    def error(self, message: str) -> NoReturn:  # type: ignore[override]
        self.exit(USAGE, f"{self.tool}: error: {message} (see `{self.prog} --help`)\n")

    def _check_value(self, action: argparse.Action, value: Any) -> None:
        # argparse's own check, with a "did you mean" and a plain list of the choices.
        if action.choices is None or value in action.choices:
            return
        if isinstance(action, argparse._SubParsersAction):
            raise argparse.ArgumentError(None, unknown_choice(value, action.choices, "command"))
        raise argparse.ArgumentError(action, unknown_choice(value, action.choices, "choice"))


def progress_kwargs(stream: Any = None) -> dict[str, float]:
    """Keyword arguments for ``tqdm`` that pace its redraws by where they go.

    On a terminal nothing changes (tqdm redraws up to ten times a second in place). When
    ``stream`` (default: stderr) is a file or a pipe, every redraw is a new record in a
    log, so the bar redraws at most every :data:`LOG_PROGRESS_INTERVAL_S` seconds: an
    hour's training logs about 120 progress records instead of tens of thousands.

    Example:
        >>> import io
        >>> progress_kwargs(io.StringIO())
        {'mininterval': 30.0, 'maxinterval': 60.0}
    """
    stream = sys.stderr if stream is None else stream
    isatty = getattr(stream, "isatty", None)
    try:
        if callable(isatty) and isatty():
            return {}
    except (OSError, ValueError):  # a closed or detached stream: treat it as a log
        pass
    return {"mininterval": LOG_PROGRESS_INTERVAL_S, "maxinterval": 2 * LOG_PROGRESS_INTERVAL_S}
