"""SceneSpec: the complete, engine-free description of one scene (frozen dataclasses).

Data flow: ``sampling.sample_scene`` -> :class:`SceneSpec` -> ``blender_backend``
(renders it) and ``writer`` (saves :meth:`SceneSpec.to_json` as ``sc%04d.json``).
:meth:`SceneSpec.from_json` reads it back, so a scene JSON is enough to re-render or
ray-cast a scene. Every field and unit is documented in ``docs/format.md``.

Units: world units (CLEVR's Blender units), degrees for angles, Cycles watts for
light energy, linear Rec.709 for ``*_linear`` colours, 8-bit sRGB for ``rgb``.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

import scenefmt
from generators import geometry
from generators.presets import MATERIALS

Vec3 = tuple[float, float, float]
Mat4 = tuple[tuple[float, float, float, float], ...]


def _vec(x) -> Vec3:
    return tuple(float(v) for v in x)  # type: ignore[return-value]


@functools.lru_cache(maxsize=64)
def chair_local_mesh(asset_id: int) -> geometry.TriMesh:
    """Canonical procedural chair ``asset_id`` (max horizontal extent 1, base z=0, flat)."""
    from assets_procedural import load_cached_chair

    m = load_cached_chair(int(asset_id))
    f = np.asarray(m.faces, dtype=np.int64)
    return geometry.TriMesh(np.asarray(m.vertices, dtype=np.float64), f, np.zeros(len(f), bool))


def _mat(x) -> Mat4:
    return tuple(tuple(float(v) for v in row) for row in np.asarray(x))  # type: ignore[return-value]


@dataclass(frozen=True)
class RenderSettings:
    """Cycles settings (CPU). Defaults chosen from measurements, see ``docs/format.md``.

    Attributes:
        resolution: square image size in pixels (>= 16).
        samples: Cycles samples per pixel (adaptive sampling off, for determinism).
        denoise: run OpenImageDenoise on the Combined pass.
        denoise_prefilter: OIDN prefilter of the albedo/normal guides (NONE/FAST/ACCURATE).
        denoise_quality: OIDN quality (HIGH/BALANCED/FAST).
        max_bounces: total light bounces.
        diffuse_bounces / glossy_bounces / transmission_bounces / volume_bounces /
            transparent_bounces: per-type caps (all scenes here are opaque and matte).
        caustics: reflective and refractive caustics.
        seed: Cycles noise seed (fixed: same scene, same noise).
        filter_width: Blackman-Harris pixel filter width in pixels.
    """

    resolution: int = 128
    samples: int = 8
    denoise: bool = True
    denoise_prefilter: str = "FAST"
    denoise_quality: str = "BALANCED"
    max_bounces: int = 4
    diffuse_bounces: int = 4
    glossy_bounces: int = 1
    transmission_bounces: int = 0
    volume_bounces: int = 0
    transparent_bounces: int = 0
    caustics: bool = False
    seed: int = 0
    filter_width: float = 1.5

    def __post_init__(self) -> None:
        if self.resolution < 16:
            raise ValueError(f"resolution must be >= 16, got {self.resolution}")
        if self.samples < 1:
            raise ValueError(f"samples must be >= 1, got {self.samples}")
        if self.max_bounces < 0:
            raise ValueError(f"max_bounces must be >= 0, got {self.max_bounces}")
        if self.denoise_prefilter not in ("NONE", "FAST", "ACCURATE"):
            raise ValueError(
                f"denoise_prefilter must be NONE/FAST/ACCURATE, got {self.denoise_prefilter!r}"
            )
        if self.denoise_quality not in ("HIGH", "BALANCED", "FAST"):
            raise ValueError(
                f"denoise_quality must be HIGH/BALANCED/FAST, got {self.denoise_quality!r}"
            )

    def to_json(self) -> dict[str, Any]:
        return {
            "engine": "CYCLES",
            "device": "CPU",
            "width": self.resolution,
            "height": self.resolution,
            "samples": self.samples,
            "adaptive_sampling": False,
            "denoise": self.denoise,
            "denoiser": "OPENIMAGEDENOISE" if self.denoise else None,
            "denoise_prefilter": self.denoise_prefilter,
            "denoise_quality": self.denoise_quality,
            "max_bounces": self.max_bounces,
            "diffuse_bounces": self.diffuse_bounces,
            "glossy_bounces": self.glossy_bounces,
            "transmission_bounces": self.transmission_bounces,
            "volume_bounces": self.volume_bounces,
            "transparent_bounces": self.transparent_bounces,
            "caustics": self.caustics,
            "seed": self.seed,
            "pixel_filter": "BLACKMAN_HARRIS",
            "filter_width": self.filter_width,
            "view_transform": "Standard",
            "rgb_encoding": "sRGB OETF of the linear Combined pass, clipped, round(255*x)",
            "tessellation": {
                "sphere": f"icosphere, {geometry.SPHERE_SUBDIVISIONS} subdivisions",
                "cylinder_segments": geometry.CYLINDER_SEGMENTS,
            },
        }

    @classmethod
    def from_json(cls, d: dict[str, Any]) -> RenderSettings:
        return cls(
            resolution=int(d["width"]),
            samples=int(d["samples"]),
            denoise=bool(d["denoise"]),
            denoise_prefilter=d["denoise_prefilter"],
            denoise_quality=d["denoise_quality"],
            max_bounces=int(d["max_bounces"]),
            diffuse_bounces=int(d["diffuse_bounces"]),
            glossy_bounces=int(d["glossy_bounces"]),
            transmission_bounces=int(d["transmission_bounces"]),
            volume_bounces=int(d["volume_bounces"]),
            transparent_bounces=int(d["transparent_bounces"]),
            caustics=bool(d["caustics"]),
            seed=int(d["seed"]),
            filter_width=float(d["filter_width"]),
        )


@dataclass(frozen=True)
class ObjectSpec:
    """One foreground object.

    Attributes:
        instance_id: >= 1; its pixels read this id in ``instances/`` (0 = background).
        shape: ``cube`` | ``sphere`` | ``cylinder`` (CLEVR) or ``chair`` (rooms).
        color: colour name (CLEVR name, or ``"asset"`` for textured assets).
        rgb: 8-bit sRGB colour (CLEVR's value); the shader's linear base colour is
            ``rgb / 255`` used as-is, exactly as CLEVR's ``render_images.py`` does.
        material: material name (see ``presets.MATERIALS``).
        size: CLEVR's r (sphere radius r; cylinder radius r and height 2r; cube edge
            2r/sqrt 2); for chairs the uniform scale applied to the canonical asset.
        size_name: ``small`` / ``large`` (CLEVR) or ``""``.
        position: object centre, world units. CLEVR objects rest on z=0, so z is the
            half height; chairs: the point on the floor under the asset's origin.
        rotation: yaw about world +z, degrees.
        asset_id: procedural asset id (chairs only).
    """

    instance_id: int
    shape: str
    color: str
    rgb: tuple[int, int, int]
    material: str
    size: float
    size_name: str
    position: Vec3
    rotation: float
    asset_id: int | None = None

    @property
    def bounding_radius_xy(self) -> float:
        """Radius of the object's bounding circle in the ground plane (CLEVR: r for all shapes)."""
        if self.shape == "chair":
            v = chair_local_mesh(int(self.asset_id or 0)).vertices
            return float(self.size * np.hypot(v[:, 0], v[:, 1]).max())
        return self.size

    def dimensions(self) -> dict[str, float]:
        """Metric dimensions of the primitive (world units)."""
        r = self.size
        if self.shape == "sphere":
            return {"radius": r}
        if self.shape == "cylinder":
            return {"radius": r, "height": 2 * r}
        if self.shape == "cube":
            return {"edge": 2 * r / math.sqrt(2)}
        return {"scale": r}

    def local_mesh(self) -> geometry.TriMesh:
        """The triangle mesh in object coordinates (centred at the object centre)."""
        d = self.dimensions()
        if self.shape == "sphere":
            return geometry.sphere_mesh(d["radius"])
        if self.shape == "cylinder":
            return geometry.cylinder_mesh(d["radius"], d["height"])
        if self.shape == "cube":
            return geometry.cube_mesh(d["edge"])
        if self.shape == "chair":
            m = chair_local_mesh(int(self.asset_id or 0))
            return geometry.TriMesh(m.vertices * self.size, m.faces, m.smooth)
        raise ValueError(f"shape: no built-in mesh for {self.shape!r}")

    def world_mesh(self) -> geometry.TriMesh:
        return self.local_mesh().transformed(self.rotation, self.position)

    def to_json(self) -> dict[str, Any]:
        d: dict[str, Any] = {
            "instance_id": self.instance_id,
            "shape": self.shape,
            "color": self.color,
            "rgb": list(self.rgb),
            "base_color_linear": [c / 255.0 for c in self.rgb],
            "material": self.material,
            "size": self.size,
            "size_name": self.size_name,
            "dimensions": self.dimensions(),
            "position": list(self.position),
            "rotation": self.rotation,
        }
        if self.asset_id is not None:
            d["asset_id"] = self.asset_id
        return d

    @classmethod
    def from_json(cls, d: dict[str, Any]) -> ObjectSpec:
        return cls(
            instance_id=int(d["instance_id"]),
            shape=d["shape"],
            color=d["color"],
            rgb=tuple(int(c) for c in d["rgb"]),  # type: ignore[arg-type]
            material=d["material"],
            size=float(d["size"]),
            size_name=d["size_name"],
            position=_vec(d["position"]),
            rotation=float(d["rotation"]),
            asset_id=None if d.get("asset_id") is None else int(d["asset_id"]),
        )


@dataclass(frozen=True)
class LightSpec:
    """An area light (square, ``size`` wide) at ``position`` aimed at ``target``."""

    name: str
    position: Vec3
    target: Vec3
    energy: float
    size: float
    color: Vec3 = (1.0, 1.0, 1.0)
    type: str = "AREA"

    def to_json(self) -> dict[str, Any]:
        return {
            "name": self.name,
            "type": self.type,
            "position": list(self.position),
            "target": list(self.target),
            "energy": self.energy,
            "energy_unit": "W (Cycles)",
            "size": self.size,
            "shape": "SQUARE",
            "color": list(self.color),
        }

    @classmethod
    def from_json(cls, d: dict[str, Any]) -> LightSpec:
        return cls(
            name=d["name"],
            position=_vec(d["position"]),
            target=_vec(d["target"]),
            energy=float(d["energy"]),
            size=float(d["size"]),
            color=_vec(d["color"]),
            type=d["type"],
        )


@dataclass(frozen=True)
class GroundSpec:
    """The ground: a square plane at z=``z`` (background, instance id 0, finite depth).

    Room presets (``type="room"``) add textures and four walls facing inwards at
    ``x, y = +-wall_half_size``, ``wall_height`` high; floor and walls are background.
    """

    size: float
    color_linear: Vec3
    roughness: float
    z: float = 0.0
    type: str = "plane"
    background_id: int | None = None
    floor_texture_id: int | None = None
    wall_texture_id: int | None = None
    wall_half_size: float | None = None
    wall_height: float | None = None
    texture_tile: float | None = None
    texture_size: int | None = None

    def floor_mesh(self) -> geometry.TriMesh:
        return geometry.plane_mesh(self.size, self.z)

    def wall_mesh(self) -> geometry.TriMesh | None:
        """The four walls (normals pointing into the room), or None."""
        if self.wall_half_size is None or self.wall_height is None:
            return None
        h, t, z = self.wall_half_size, self.wall_height, self.z
        quads = [
            [(-h, h, z), (h, h, z), (h, h, z + t), (-h, h, z + t)],  # +y wall, normal -y
            [(h, -h, z), (-h, -h, z), (-h, -h, z + t), (h, -h, z + t)],  # -y wall, normal +y
            [(h, h, z), (h, -h, z), (h, -h, z + t), (h, h, z + t)],  # +x wall, normal -x
            [(-h, -h, z), (-h, h, z), (-h, h, z + t), (-h, -h, z + t)],  # -x wall, normal +x
        ]
        v = np.array([p for q in quads for p in q], dtype=np.float64)
        f = np.array([[4 * i, 4 * i + 1, 4 * i + 2] for i in range(4)]
                     + [[4 * i, 4 * i + 2, 4 * i + 3] for i in range(4)], dtype=np.int64)  # fmt: skip
        return geometry.TriMesh(v, f, np.zeros(len(f), bool))

    def mesh(self) -> geometry.TriMesh:
        """Floor (+ walls): everything that is background."""
        walls = self.wall_mesh()
        if walls is None:
            return self.floor_mesh()
        return geometry.concat_meshes([self.floor_mesh(), walls])[0]

    def to_json(self) -> dict[str, Any]:
        d = {
            "type": self.type,
            "size": self.size,
            "z": self.z,
            "color_linear": list(self.color_linear),
            "roughness": self.roughness,
            "instance_id": 0,
        }
        for k in ("background_id", "floor_texture_id", "wall_texture_id", "wall_half_size",
                  "wall_height", "texture_tile", "texture_size"):  # fmt: skip
            if getattr(self, k) is not None:
                d[k] = getattr(self, k)
        return d

    @classmethod
    def from_json(cls, d: dict[str, Any]) -> GroundSpec:
        return cls(
            size=float(d["size"]),
            color_linear=_vec(d["color_linear"]),
            roughness=float(d["roughness"]),
            z=float(d["z"]),
            type=d["type"],
            background_id=d.get("background_id"),
            floor_texture_id=d.get("floor_texture_id"),
            wall_texture_id=d.get("wall_texture_id"),
            wall_half_size=d.get("wall_half_size"),
            wall_height=d.get("wall_height"),
            texture_tile=d.get("texture_tile"),
            texture_size=d.get("texture_size"),
        )


@dataclass(frozen=True)
class WorldSpec:
    """Uniform environment light (what a ray that hits nothing sees)."""

    color_linear: Vec3
    strength: float

    def to_json(self) -> dict[str, Any]:
        return {"color_linear": list(self.color_linear), "strength": self.strength}

    @classmethod
    def from_json(cls, d: dict[str, Any]) -> WorldSpec:
        return cls(_vec(d["color_linear"]), float(d["strength"]))


@dataclass(frozen=True)
class ViewSpec:
    """One camera.

    Attributes:
        azimuth_deg / elevation_deg / radius: where the camera sits on its sphere
            around ``look_at`` (azimuth from +x towards +y).
        cam_to_world: 4x4, OpenCV axes (x right, y down, z forward).
        lens_mm / sensor_width_mm: Blender camera (sensor fit HORIZONTAL).
        look_at: the point the optical axis passes through.
    """

    azimuth_deg: float
    elevation_deg: float
    radius: float
    cam_to_world: Mat4
    lens_mm: float
    sensor_width_mm: float
    look_at: Vec3 = (0.0, 0.0, 0.0)

    def K(self, width: int, height: int) -> np.ndarray:
        """3x3 pixel intrinsics at ``width`` x ``height`` (pixel centres at +0.5)."""
        return geometry.intrinsics(self.lens_mm, self.sensor_width_mm, width, height)

    def c2w(self) -> np.ndarray:
        return np.array(self.cam_to_world, dtype=np.float64)

    def to_json(self, image: str, width: int, height: int) -> dict[str, Any]:
        return {
            "image": image,
            "K": self.K(width, height).tolist(),
            "cam_to_world": [list(r) for r in self.cam_to_world],
            "azimuth_deg": self.azimuth_deg,
            "elevation_deg": self.elevation_deg,
            "radius": self.radius,
            "look_at": list(self.look_at),
            "lens_mm": self.lens_mm,
            "sensor_width_mm": self.sensor_width_mm,
            "sensor_fit": "HORIZONTAL",
        }

    @classmethod
    def from_json(cls, d: dict[str, Any]) -> ViewSpec:
        return cls(
            azimuth_deg=float(d["azimuth_deg"]),
            elevation_deg=float(d["elevation_deg"]),
            radius=float(d["radius"]),
            cam_to_world=_mat(d["cam_to_world"]),
            lens_mm=float(d["lens_mm"]),
            sensor_width_mm=float(d["sensor_width_mm"]),
            look_at=_vec(d["look_at"]),
        )


@dataclass(frozen=True)
class SceneSpec:
    """Everything needed to render one scene; a pure function of (preset, split, index, seed).

    Attributes:
        preset: name of the preset whose rules sampled the scene.
        split / index: where the scene sits in the dataset.
        seed: the dataset seed (``--seed``).
        scene_seed: ``seed * 1_000_000 + split_code * 100_000 + index``.
        attempt: which sampling attempt passed the visibility check (0 = first);
            attempt k draws from ``numpy.random.default_rng([scene_seed, k])`` for
            k >= 1 and from ``default_rng(scene_seed)`` for k = 0.
        objects / lights / ground / world / views: the scene content.
        render: Cycles settings.
        extra: additional top-level JSON keys (e.g. the grayscale flag).
    """

    preset: str
    split: str
    index: int
    seed: int
    scene_seed: int
    attempt: int
    objects: tuple[ObjectSpec, ...]
    lights: tuple[LightSpec, ...]
    ground: GroundSpec
    world: WorldSpec
    views: tuple[ViewSpec, ...]
    render: RenderSettings = field(default_factory=RenderSettings)
    extra: tuple[tuple[str, Any], ...] = ()

    @property
    def n_views(self) -> int:
        return len(self.views)

    def with_render(self, render: RenderSettings) -> SceneSpec:
        return replace(self, render=render)

    def meshes(self) -> tuple[list[geometry.TriMesh], list[int]]:
        """World-space meshes of ground + objects and their instance ids (ground = 0)."""
        meshes = [self.ground.mesh()]
        ids = [0]
        for o in self.objects:
            meshes.append(o.world_mesh())
            ids.append(o.instance_id)
        return meshes, ids

    def record(self, image_names: list[str] | None = None) -> scenefmt.SceneRecord:
        """The scene record (``sc%04d.json``); ``image_names`` are the view file names."""
        w = h = self.render.resolution
        if image_names is None:
            image_names = [f"view{v:02d}.png" for v in range(self.n_views)]
        used = sorted({o.material for o in self.objects})
        views = []
        for v, n in zip(self.views, image_names, strict=True):
            d = v.to_json(n, w, h)
            views.append(scenefmt.ViewRecord.from_json(d))
        extra: dict[str, Any] = {
            "scene_seed": self.scene_seed,
            "attempt": self.attempt,
            "rng": "numpy.random.default_rng(scene_seed) for attempt 0, "
            "default_rng([scene_seed, attempt]) otherwise",
            "world_up": "+z",
            "units": "world units (CLEVR Blender units); angles in degrees",
            "materials": {m: {"shader": "principled_bsdf", **MATERIALS[m]} for m in used},
            "lights": [light.to_json() for light in self.lights],
            "ground": self.ground.to_json(),
            "world": self.world.to_json(),
            "render": self.render.to_json(),
        }
        for k, v in self.extra:
            extra[k] = v
        return scenefmt.SceneRecord(
            preset=self.preset,
            split=self.split,
            index=self.index,
            seed=self.seed,
            views=tuple(views),
            objects=tuple(o.to_json() for o in self.objects),
            extra=extra,
        )

    def to_json(self, image_names: list[str] | None = None) -> dict[str, Any]:
        """The scene JSON (``sc%04d.json``): :meth:`record` as a dict."""
        return self.record(image_names).to_json()

    @classmethod
    def from_json(cls, d: dict[str, Any]) -> SceneSpec:
        known = {
            "format", "preset", "split", "index", "seed", "scene_seed", "attempt", "rng",
            "camera_convention", "depth", "world_up", "units", "objects", "materials",
            "lights", "ground", "world", "views", "render",
        }  # fmt: skip
        return cls(
            preset=d["preset"],
            split=d["split"],
            index=int(d["index"]),
            seed=int(d["seed"]),
            scene_seed=int(d["scene_seed"]),
            attempt=int(d["attempt"]),
            objects=tuple(ObjectSpec.from_json(o) for o in d["objects"]),
            lights=tuple(LightSpec.from_json(x) for x in d["lights"]),
            ground=GroundSpec.from_json(d["ground"]),
            world=WorldSpec.from_json(d["world"]),
            views=tuple(ViewSpec.from_json(v) for v in d["views"]),
            render=RenderSettings.from_json(d["render"]),
            extra=tuple((k, v) for k, v in d.items() if k not in known),
        )
