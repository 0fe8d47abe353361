"""Input checks shared by the metric modules (internal).

Every public metric validates its tensors here so the error messages read the same
everywhere: the argument's name, what was expected and what arrived.
"""

from __future__ import annotations

import torch
from torch import Tensor


def describe(x: object) -> str:
    """Short description of a value for error messages (shape and dtype for tensors)."""
    if isinstance(x, Tensor):
        return f"tensor of shape {tuple(x.shape)} and dtype {x.dtype}"
    return f"{type(x).__name__}"


def require_tensor(name: str, x: object, expected: str) -> Tensor:
    """Raise ValueError unless ``x`` is a torch tensor."""
    if not isinstance(x, Tensor):
        # ValueError, not TypeError: the house rule is one exception type at boundaries.
        raise ValueError(f"{name}: expected a torch.Tensor {expected}, got {describe(x)}")  # noqa: TRY004
    return x


def require_integer(name: str, x: Tensor, expected: str) -> None:
    """Raise ValueError unless ``x`` has an integer (non-bool) dtype."""
    if x.dtype == torch.bool or x.is_floating_point() or x.is_complex():
        raise ValueError(f"{name}: expected an integer tensor {expected}, got {describe(x)}")


def require_float(name: str, x: Tensor, expected: str) -> None:
    """Raise ValueError unless ``x`` has a floating dtype."""
    if not x.is_floating_point():
        raise ValueError(f"{name}: expected a floating tensor {expected}, got {describe(x)}")


def require_same_shape(name: str, x: Tensor, ref_name: str, ref: Tensor) -> None:
    """Raise ValueError unless ``x`` has the shape of ``ref``."""
    if x.shape != ref.shape:
        raise ValueError(
            f"{name}: expected the shape of {ref_name} {tuple(ref.shape)}, got {tuple(x.shape)}"
        )


def require_batched(name: str, x: Tensor, expected: str, min_dim: int = 2) -> None:
    """Raise ValueError unless ``x`` has at least ``min_dim`` dims."""
    if x.dim() < min_dim:
        raise ValueError(f"{name}: expected {expected}, got {describe(x)}")
