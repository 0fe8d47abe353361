"""Blender/Cycles backend: SceneSpec -> per-view passes. The ONLY module importing bpy.

Data flow: ``pipeline`` worker -> :class:`BlenderSession.render_scene` ->
:class:`ViewPasses` (linear RGB, instance ids, planar depth) -> ``writer``.

One session (one Blender instance in one process) renders many scenes: each scene
is built once (objects, materials, lights, world) and its views are rendered by
moving the camera. RGB, instance ids and depth of a view come from the SAME render:
Cycles writes the Combined, ``Object Index`` and ``Depth`` (Z) passes into one
multilayer EXR (Blender 5.0 stores it as a multi-part file; we read the parts with
OpenImageIO ``seek_subimage``). Index and Z passes are written by the first
camera sample, which Cycles shoots through the pixel centre, so they are exact
(not anti-aliased) and deterministic; ground-plane pixels read id 0 and a finite
depth; rays that hit nothing read Blender's 1e10, which we turn into ``inf``.

``bpy`` is imported lazily by :func:`import_bpy`; if it is missing the CLI prints a
one-line error and exits with status 2 (see ``cli``).
"""

from __future__ import annotations

import contextlib
import math
import os
import shutil
import tempfile
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from generators import geometry
from generators.presets import MATERIALS
from generators.spec import RenderSettings, SceneSpec

#: Blender's depth for rays that hit nothing.
_BLENDER_NO_HIT = 1e9


class BpyMissingError(ImportError):
    """``bpy`` cannot be imported."""


def import_bpy():
    """Import and return ``bpy``; :class:`BpyMissingError` with an install hint otherwise."""
    try:
        with quiet_output():  # Cycles prints a CUDA-loader warning on import
            import bpy
    except ImportError as e:
        raise BpyMissingError(
            f"cannot import bpy ({e}); install Blender's Python module: pip install bpy==5.0.1 "
            "(Python 3.11, numpy<2)"
        ) from e
    return bpy


def bpy_available() -> bool:
    """True if ``bpy`` can be found (without importing it)."""
    import importlib.util

    return importlib.util.find_spec("bpy") is not None


@dataclass(frozen=True)
class ViewPasses:
    """Raw passes of one rendered view.

    Attributes:
        rgb_linear: float32 [H, W, 3], scene-linear Combined pass (denoised if enabled).
        ids: uint8 [H, W], instance ids from the object index pass (0 = background).
        depth_z: float32 [H, W], planar depth (camera z, world units); inf = no hit.
        render_s: seconds spent inside Cycles' render call for this view.
    """

    rgb_linear: np.ndarray
    ids: np.ndarray
    depth_z: np.ndarray
    render_s: float


@contextlib.contextmanager
def quiet_output() -> Iterator[None]:
    """Silence Blender's C-level stdout/stderr chatter (progress lines, 'Saved:') inside a
    ``with`` block (file descriptors 1 and 2 point at /dev/null, then back)."""
    null = os.open(os.devnull, os.O_WRONLY)
    saved = [os.dup(1), os.dup(2)]
    try:
        os.dup2(null, 1)
        os.dup2(null, 2)
        yield
    finally:
        os.dup2(saved[0], 1)
        os.dup2(saved[1], 2)
        for fd in (*saved, null):
            os.close(fd)


def read_multilayer_exr(path: str | os.PathLike) -> dict[str, np.ndarray]:
    """Read every part of a Blender 5.0 multilayer EXR.

    Returns:
        ``{pass name: float32 [H, W, C]}`` keyed by the part's pass name, e.g.
        ``"Combined"`` (RGBA), ``"Depth"`` (Z), ``"Object Index"`` (X).
    """
    import OpenImageIO as oiio

    inp = oiio.ImageInput.open(str(path))
    if inp is None:
        raise OSError(f"cannot open {path}: {oiio.geterror()}")
    out: dict[str, np.ndarray] = {}
    try:
        i = 0
        while inp.seek_subimage(i, 0):
            names = inp.spec().channelnames
            # "ViewLayer.Depth.Z" -> "Depth"
            key = names[0].split(".")[-2] if names[0].count(".") >= 2 else names[0]
            arr = inp.read_image(format="float")
            if arr is None:
                raise OSError(f"cannot read part {i} of {path}: {inp.geterror()}")
            out[key] = np.asarray(arr, dtype=np.float32).reshape(
                inp.spec().height, inp.spec().width, len(names)
            )
            i += 1
    finally:
        inp.close()
    return out


class BlenderSession:
    """One Blender instance that renders many scenes.

    Args:
        threads: Cycles CPU threads (>= 1).
        tmp_dir: where the per-view EXR files go (a private temp dir by default).
    """

    def __init__(self, threads: int = 1, tmp_dir: str | os.PathLike | None = None) -> None:
        if threads < 1:
            raise ValueError(f"threads must be >= 1, got {threads}")
        self.bpy = import_bpy()
        self.threads = int(threads)
        self._own_tmp = tmp_dir is None
        self.tmp_dir = (
            Path(tempfile.mkdtemp(prefix="svorf_bpy_")) if tmp_dir is None else Path(tmp_dir)
        )
        self.tmp_dir.mkdir(parents=True, exist_ok=True)
        if any(c in str(self.tmp_dir) for c in "{}#"):
            raise ValueError(f"tmp_dir must not contain braces or '#': {self.tmp_dir}")
        self.scenes_rendered = 0
        with quiet_output():
            self.bpy.ops.wm.read_factory_settings(use_empty=True)

    def close(self) -> None:
        if self._own_tmp:
            shutil.rmtree(self.tmp_dir, ignore_errors=True)

    # ------------------------------------------------------------------ settings

    def _configure(self, render: RenderSettings) -> None:
        bpy = self.bpy
        sc = bpy.context.scene
        r = sc.render
        r.engine = "CYCLES"
        r.resolution_x = r.resolution_y = render.resolution
        r.resolution_percentage = 100
        r.pixel_aspect_x = r.pixel_aspect_y = 1.0
        r.film_transparent = False
        r.filter_size = render.filter_width
        r.threads_mode = "FIXED"
        r.threads = self.threads
        r.use_persistent_data = False
        c = sc.cycles
        c.device = "CPU"
        c.samples = render.samples
        c.use_adaptive_sampling = False
        c.seed = render.seed
        c.use_animated_seed = False
        c.pixel_filter_type = "BLACKMAN_HARRIS"
        c.use_denoising = render.denoise
        if render.denoise:
            c.denoiser = "OPENIMAGEDENOISE"
            c.denoising_input_passes = "RGB_ALBEDO_NORMAL"
            c.denoising_prefilter = render.denoise_prefilter
            c.denoising_quality = render.denoise_quality
        c.max_bounces = render.max_bounces
        c.diffuse_bounces = render.diffuse_bounces
        c.glossy_bounces = render.glossy_bounces
        c.transmission_bounces = render.transmission_bounces
        c.volume_bounces = render.volume_bounces
        c.transparent_max_bounces = render.transparent_bounces
        c.caustics_reflective = render.caustics
        c.caustics_refractive = render.caustics
        vl = sc.view_layers[0]
        vl.use_pass_combined = True
        vl.use_pass_z = True
        vl.use_pass_object_index = True
        ims = r.image_settings
        ims.media_type = "MULTI_LAYER_IMAGE"
        ims.color_depth = "32"  # full float: the Z pass must stay exact
        ims.exr_codec = "NONE"  # temp file, read once: skip compression
        sc.view_settings.view_transform = "Standard"
        sc.view_settings.look = "None"
        sc.view_settings.exposure = 0.0
        sc.view_settings.gamma = 1.0

    # ------------------------------------------------------------------ scene

    def _clear(self) -> None:
        d = self.bpy.data
        for coll in (d.objects, d.meshes, d.materials, d.lights, d.cameras, d.worlds, d.images):
            items = list(coll)
            if items:
                d.batch_remove(items)

    def _mesh(self, name: str, mesh: geometry.TriMesh):
        me = self.bpy.data.meshes.new(name)
        me.from_pydata(mesh.vertices.tolist(), [], mesh.faces.tolist())
        me.polygons.foreach_set("use_smooth", mesh.smooth.tolist())
        me.update()
        return me

    def _material(
        self, name: str, base_color_linear, roughness: float, specular: float, metallic: float
    ):
        mat = self.bpy.data.materials.new(name)
        bsdf = next(n for n in mat.node_tree.nodes if n.bl_idname == "ShaderNodeBsdfPrincipled")
        bsdf.inputs["Base Color"].default_value = (*base_color_linear, 1.0)
        bsdf.inputs["Roughness"].default_value = roughness
        bsdf.inputs["Specular IOR Level"].default_value = specular
        bsdf.inputs["Metallic"].default_value = metallic
        return mat

    def _textured_material(
        self, name: str, texture_id: int, size: int, tile: float, roughness: float
    ):
        """Principled BSDF whose base colour is a procedural texture, box-projected in
        object coordinates (one repeat every ``tile`` world units; no UVs needed)."""
        from assets_procedural import cached_texture_path

        mat = self.bpy.data.materials.new(name)
        nt = mat.node_tree
        bsdf = next(n for n in nt.nodes if n.bl_idname == "ShaderNodeBsdfPrincipled")
        bsdf.inputs["Roughness"].default_value = roughness
        bsdf.inputs["Specular IOR Level"].default_value = 0.25
        coord = nt.nodes.new("ShaderNodeTexCoord")
        mapping = nt.nodes.new("ShaderNodeMapping")
        mapping.inputs["Scale"].default_value = (1.0 / tile, 1.0 / tile, 1.0 / tile)
        tex = nt.nodes.new("ShaderNodeTexImage")
        tex.image = self.bpy.data.images.load(str(cached_texture_path(texture_id, size)))
        tex.image.colorspace_settings.name = "sRGB"
        tex.projection = "BOX"
        tex.extension = "REPEAT"
        nt.links.new(coord.outputs["Object"], mapping.inputs["Vector"])
        nt.links.new(mapping.outputs["Vector"], tex.inputs["Vector"])
        nt.links.new(tex.outputs["Color"], bsdf.inputs["Base Color"])
        return mat

    def _add_object(
        self,
        name: str,
        mesh: geometry.TriMesh,
        material,
        pass_index: int,
        location=(0.0, 0.0, 0.0),
        yaw_deg: float = 0.0,
    ):
        obj = self.bpy.data.objects.new(name, self._mesh(name, mesh))
        obj.data.materials.append(material)
        obj.location = location
        obj.rotation_euler = (0.0, 0.0, math.radians(yaw_deg))
        obj.pass_index = pass_index
        # Cycles moves the hit point of smooth-shaded faces towards the smooth surface
        # (default offset 0.1), which would bend the Z pass off the true triangles.
        obj.shadow_terminator_geometry_offset = 0.0
        self.bpy.context.scene.collection.objects.link(obj)
        return obj

    def build(self, spec: SceneSpec) -> None:
        """Replace whatever scene is loaded with ``spec`` (camera at view 0)."""
        bpy = self.bpy
        from mathutils import Vector

        self._clear()
        with quiet_output():  # the first Cycles setting probes for CUDA and warns on stderr
            self._configure(spec.render)
        sc = bpy.context.scene
        g = spec.ground
        if g.floor_texture_id is None:
            ground_mat = self._material("ground", g.color_linear, g.roughness, 0.25, 0.0)
        else:
            ground_mat = self._textured_material(
                "floor",
                g.floor_texture_id,
                g.texture_size or 256,
                g.texture_tile or 4.0,
                g.roughness,
            )
        self._add_object("ground", g.floor_mesh(), ground_mat, 0)
        walls = g.wall_mesh()
        if walls is not None:
            if g.wall_texture_id is None:
                wall_mat = self._material("walls", g.color_linear, g.roughness, 0.25, 0.0)
            else:
                wall_mat = self._textured_material(
                    "walls",
                    g.wall_texture_id,
                    g.texture_size or 256,
                    g.texture_tile or 4.0,
                    g.roughness,
                )
            self._add_object("walls", walls, wall_mat, 0)
        for o in spec.objects:
            m = MATERIALS[o.material]
            mat = self._material(
                f"mat{o.instance_id}", [c / 255.0 for c in o.rgb],
                m["roughness"], m["specular_ior_level"], m["metallic"],
            )  # fmt: skip
            self._add_object(
                f"obj{o.instance_id}", o.local_mesh(), mat, o.instance_id, o.position, o.rotation
            )
        for light in spec.lights:
            ld = bpy.data.lights.new(light.name, "AREA")
            ld.energy = light.energy
            ld.size = light.size
            ld.shape = "SQUARE"
            ld.color = light.color
            lo = bpy.data.objects.new(light.name, ld)
            lo.location = light.position
            direction = Vector(light.target) - Vector(light.position)
            lo.rotation_euler = direction.to_track_quat("-Z", "Y").to_euler()
            sc.collection.objects.link(lo)
        world = bpy.data.worlds.new("world")
        bg = next(n for n in world.node_tree.nodes if n.bl_idname == "ShaderNodeBackground")
        bg.inputs["Color"].default_value = (*spec.world.color_linear, 1.0)
        bg.inputs["Strength"].default_value = spec.world.strength
        sc.world = world
        cam = bpy.data.cameras.new("camera")
        cam.sensor_fit = "HORIZONTAL"
        cam.clip_start = 0.1
        cam.clip_end = 1000.0
        cam_obj = bpy.data.objects.new("camera", cam)
        sc.collection.objects.link(cam_obj)
        sc.camera = cam_obj
        self._set_view(spec, 0)

    def _set_view(self, spec: SceneSpec, view: int) -> None:
        from mathutils import Matrix

        v = spec.views[view]
        cam_obj = self.bpy.context.scene.camera
        cam_obj.data.lens = v.lens_mm
        cam_obj.data.sensor_width = v.sensor_width_mm
        cam_obj.matrix_world = Matrix((v.c2w() @ geometry.CV_TO_BLENDER).tolist())

    # ------------------------------------------------------------------ render

    def render_view(self, spec: SceneSpec, view: int) -> ViewPasses:
        """Render view ``view`` of the currently built ``spec``."""
        bpy = self.bpy
        self._set_view(spec, view)
        path = self.tmp_dir / f"view{view:02d}.exr"
        bpy.context.scene.render.filepath = str(path)
        t0 = time.perf_counter()
        with quiet_output():
            bpy.ops.render.render(write_still=True)
        dt = time.perf_counter() - t0
        passes = read_multilayer_exr(path)
        path.unlink(missing_ok=True)
        try:
            rgb = passes["Combined"][..., :3]
            z = passes["Depth"][..., 0]
            idx = passes["Object Index"][..., 0]
        except KeyError as e:
            raise RuntimeError(f"render of view {view} lacks pass {e}; got {sorted(passes)}") from e
        depth = np.where(z >= _BLENDER_NO_HIT, np.inf, z).astype(np.float32)
        ids = np.rint(idx)
        if ids.min() < 0 or ids.max() > 255:
            raise RuntimeError(f"object index pass out of uint8 range: {ids.min()}..{ids.max()}")
        return ViewPasses(
            np.ascontiguousarray(rgb, dtype=np.float32), ids.astype(np.uint8), depth, dt
        )

    def render_scene(self, spec: SceneSpec) -> list[ViewPasses]:
        """Build ``spec`` once and render all its views (camera moved between views)."""
        self.build(spec)
        out = [self.render_view(spec, v) for v in range(spec.n_views)]
        self.scenes_rendered += 1
        return out
