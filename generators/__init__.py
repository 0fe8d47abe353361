"""Blender/Cycles dataset generator (uORF-style multi-view object-centric splits).

Data flow::

    presets (registry) -> sampling.make_scene (pure Python, seeded) -> spec.SceneSpec
      -> blender_backend (the only bpy import, lazy) -> imageops -> writer (scenefmt)
    pipeline.generate_dataset(GenerateConfig) drives it, running worker.render_one in
    worker processes (or on Ray actors, ray_backend); cli (``generate``) wraps it;
    verify checks a split; preview draws a contact sheet; testing writes ray-cast
    fixtures without bpy.

``generate_dataset`` and ``GenerateConfig`` are re-exported lazily (importing this
package stays cheap).
"""

from __future__ import annotations

__all__ = ["GenerateConfig", "GenerateSummary", "generate_dataset"]


def __getattr__(name: str):
    if name in __all__:
        from generators import pipeline

        return getattr(pipeline, name)
    raise AttributeError(f"module 'generators' has no attribute {name!r}")
