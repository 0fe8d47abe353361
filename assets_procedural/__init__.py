"""Procedural assets: parametric chairs and floor/wall textures, seeded and cached.

Where this sits in the data flow::

    preset + seed -> scene sampler (Room presets) --picks--> chair ids, background id
        background id -> background_params() -> (floor texture id, wall texture id)
    blender backend: cached_chair_path(id) -> PLY, cached_texture_path(id, size) -> PNG

No downloads, no ShapeNet: every asset is a pure function of an integer id and a
generator version, so a scene JSON that stores the ids can always be re-rendered.
This package imports neither torch nor bpy (numpy, scipy, trimesh, pillow only).

Modules:

* :mod:`assets_procedural.chairs`: ``build_chair``, ``chair_mesh`` (canonical frame: max
  horizontal extent 1.0, footprint centred on x=y=0, min z 0, front towards -y).
* :mod:`assets_procedural.chair_spec`: ``ChairParams`` and ``chair_params`` (the draws
  from an id), re-exported by ``chairs``.
* :mod:`assets_procedural.textures`: ``texture_params``, ``texture_image``,
  ``background_params`` (50 backgrounds over a pool of 50 textures by default).
* :mod:`assets_procedural.cache`: atomic on-disk cache keyed by (kind, id, version).
* :mod:`assets_procedural.ids`: ``check_id``, the one validity check of every asset id.
* :mod:`assets_procedural.distinct`: shape descriptors and ``count_distinct``
  (``python -m assets_procedural.distinct --n 1200``).
* :mod:`assets_procedural.preview`: contact sheets for eyeballing (matplotlib).
"""

from assets_procedural.cache import (
    cached_chair_path,
    cached_texture_path,
    default_cache_dir,
    load_cached_chair,
)
from assets_procedural.chairs import (
    ARM_STYLES,
    BACK_STYLES,
    CHAIR_GENERATOR_VERSION,
    HEIGHT_RANGE,
    LEG_SECTIONS,
    LEG_STYLES,
    SEAT_SHAPES,
    ChairParams,
    ChairPart,
    build_chair,
    build_chair_parts,
    chair_mesh,
    chair_params,
)
from assets_procedural.textures import (
    FAMILIES,
    FLOOR_FAMILIES,
    N_TEXTURES_DEFAULT,
    TEXTURE_GENERATOR_VERSION,
    WALL_FAMILIES,
    TextureParams,
    background_params,
    texture_image,
    texture_params,
)

__all__ = [
    "ARM_STYLES",
    "BACK_STYLES",
    "CHAIR_GENERATOR_VERSION",
    "DESCRIPTOR_NAMES",
    "FAMILIES",
    "FLOOR_FAMILIES",
    "HEIGHT_RANGE",
    "LEG_SECTIONS",
    "LEG_STYLES",
    "N_TEXTURES_DEFAULT",
    "SEAT_SHAPES",
    "TEXTURE_GENERATOR_VERSION",
    "WALL_FAMILIES",
    "ChairParams",
    "ChairPart",
    "TextureParams",
    "background_params",
    "build_chair",
    "build_chair_parts",
    "cached_chair_path",
    "cached_texture_path",
    "chair_descriptor",
    "chair_mesh",
    "chair_params",
    "count_distinct",
    "default_cache_dir",
    "load_cached_chair",
    "texture_image",
    "texture_params",
]

_LAZY = {"DESCRIPTOR_NAMES", "chair_descriptor", "count_distinct"}


def __getattr__(name: str):
    # distinct is loaded on first use, so `python -m assets_procedural.distinct`
    # does not find its own module already imported by the package.
    if name in _LAZY:
        from assets_procedural import distinct

        return getattr(distinct, name)
    raise AttributeError(f"module 'assets_procedural' has no attribute {name!r}")
