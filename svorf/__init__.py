"""svorf package: PyTorch implementation of sVORF (Qi et al., NeurIPS 2023).

Public API (re-exported lazily so that ``import svorf.config`` does not import torch):

- ``ModelConfig``, ``model_config`` (svorf.config)
- ``SVORF``, ``RenderOutput`` (svorf.model)
- ``volume_render``, ``sample_stratified``, ``sample_pdf``, ``clip_rays_to_box`` (svorf.render)
- ``distortion_loss``, ``connectivity_loss`` (svorf.losses)
- ``move_object``, ``swap_background`` (svorf.edit)
"""

from __future__ import annotations

import importlib
from typing import Any

_EXPORTS = {
    "ModelConfig": "svorf.config",
    "model_config": "svorf.config",
    "SVORF": "svorf.model",
    "RenderOutput": "svorf.model",
    "volume_render": "svorf.render",
    "sample_stratified": "svorf.render",
    "sample_pdf": "svorf.render",
    "clip_rays_to_box": "svorf.render",
    "distortion_loss": "svorf.losses",
    "connectivity_loss": "svorf.losses",
    "move_object": "svorf.edit",
    "swap_background": "svorf.edit",
}

__all__ = [
    "SVORF",
    "ModelConfig",
    "RenderOutput",
    "clip_rays_to_box",
    "connectivity_loss",
    "distortion_loss",
    "model_config",
    "move_object",
    "sample_pdf",
    "sample_stratified",
    "swap_background",
    "volume_render",
]


def __getattr__(name: str) -> Any:
    if name in _EXPORTS:
        return getattr(importlib.import_module(_EXPORTS[name]), name)
    raise AttributeError(f"module 'svorf' has no attribute {name!r}")
