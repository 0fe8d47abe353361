"""The on-disk dataset contract, defined once (docs/format.md is its description).

Writers (``generators``) and readers (``svorf.data``, ``benchmark``) both import
this package, so nothing else re-implements file names or conventions. It
imports neither torch nor bpy; OpenImageIO is loaded lazily for depth EXRs.

Layout of one split folder (e.g. ``data/clevr567/train/``)::

    {idx:05d}_sc{scene:04d}_az{view:02d}.png        RGB, 8-bit sRGB, 3 channels
    {stem}_RT.txt                                    4x4 camera-to-world, OpenCV axes
    {stem}_azi_rot.txt                               3x3 rotation about world z by the azimuth
    {stem}_mask.png                                  uORF-compatible grey-level mask
                                                     (sentinel block, ``sentinel_size``)
    instances/{stem}.png                             8-bit instance ids, 0 = background
    depth/{stem}.exr                                 float32 planar depth (camera z), world units
    sc{scene:04d}.json                               full scene record (written last)
    manifest.json                                    split-level metadata

The two JSON files are :class:`SceneRecord` and :class:`Manifest` (``records.py``), which
every writer builds and every reader reads; :func:`dataset_fingerprint` hashes them.
``errors.py`` holds :class:`DatasetError` (a split folder that cannot be read, one line
naming the fix) and ``uorf.py`` the reader of plain uORF-layout folders.

``idx`` is the global view index ``scene * n_views + view``. A manipulation split
(``generate --split manip``) adds uORF's manipulation files: see :class:`ManipLayout`.
"""

from scenefmt.errors import DatasetError, missing_file, read_file
from scenefmt.io import (
    atomic_write_bytes,
    atomic_write_json,
    default_file_mode,
    mkstemp_beside,
    read_depth_exr,
    read_instances,
    read_json,
    read_matrix_txt,
    read_movement_txt,
    read_rgb,
    write_depth_exr,
    write_instances,
    write_mask,
    write_matrix_txt,
    write_movement_txt,
    write_rgb,
)
from scenefmt.layout import (
    FORMAT_VERSION,
    LUMA_REC601,
    MANIP_MASK_OFF,
    MANIP_MASK_ON,
    MANIP_SPLIT,
    MANIP_VARIANTS,
    MASK_BG_LEVEL,
    MASK_SENTINEL_LEVEL,
    MIN_UORF_MASK_SIZE,
    ManipLayout,
    SplitLayout,
    instances_from_uorf_mask,
    is_scene_complete,
    manip_mask,
    sentinel_size,
    uorf_mask_from_instances,
)
from scenefmt.records import (
    MANIFEST_FORMAT,
    SCENE_FORMAT,
    Manifest,
    SceneRecord,
    ViewRecord,
    dataset_fingerprint,
    legacy_fingerprint,
)

__all__ = [
    "FORMAT_VERSION",
    "LUMA_REC601",
    "MANIFEST_FORMAT",
    "MANIP_MASK_OFF",
    "MANIP_MASK_ON",
    "MANIP_SPLIT",
    "MANIP_VARIANTS",
    "MASK_BG_LEVEL",
    "MASK_SENTINEL_LEVEL",
    "MIN_UORF_MASK_SIZE",
    "SCENE_FORMAT",
    "DatasetError",
    "Manifest",
    "ManipLayout",
    "SceneRecord",
    "SplitLayout",
    "ViewRecord",
    "atomic_write_bytes",
    "atomic_write_json",
    "dataset_fingerprint",
    "default_file_mode",
    "instances_from_uorf_mask",
    "is_scene_complete",
    "legacy_fingerprint",
    "manip_mask",
    "missing_file",
    "mkstemp_beside",
    "read_depth_exr",
    "read_file",
    "read_instances",
    "read_json",
    "read_matrix_txt",
    "read_movement_txt",
    "read_rgb",
    "sentinel_size",
    "uorf_mask_from_instances",
    "write_depth_exr",
    "write_instances",
    "write_mask",
    "write_matrix_txt",
    "write_movement_txt",
    "write_rgb",
]
