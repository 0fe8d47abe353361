"""Asset ids: the one check that an id (chair, texture, background, pool size) is valid.

Where this sits: below every id-keyed module of the package. ``chairs.chair_params``,
``textures.texture_params`` / ``background_params`` and the ``cache`` paths all call
:func:`check_id` on the ids they are given, so one id is accepted or refused (with the
same message) wherever it enters.
"""

from __future__ import annotations

from numbers import Integral

__all__ = ["check_id"]


def check_id(value: object, name: str) -> int:
    """``value`` as an ``int`` when it is a non-negative integer (``bool`` is not).

    Args:
        value: the id to check (any integral type, e.g. ``int`` or ``numpy.int64``).
        name: the argument's name, for the message (``"asset_id"``, ``"texture_id"``).

    Returns:
        ``int(value)``.

    Raises:
        TypeError: ``value`` is not an integer (or is a ``bool``).
        ValueError: ``value`` is negative.
    """
    if isinstance(value, bool) or not isinstance(value, Integral):
        raise TypeError(f"{name} must be a non-negative int, got {type(value).__name__}")
    if value < 0:
        raise ValueError(f"{name} must be a non-negative int, got {value}")
    return int(value)
