"""svorf.data and svorf.synthetic: dataset reading, rays, resizing and ray sampling.

All fixtures are tiny analytic splits written by ``svorf.synthetic`` into ``tmp_path``.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from scenefmt import SplitLayout, read_json
from svorf.data import (
    RAY_SAMPLING,
    DatasetError,
    MultiViewDataset,
    RaySampler,
    dataset_fingerprint,
    object_heavy_rays,
    pixel_rays,
    salient_pixels,
)
from svorf.synthetic import write_synthetic_split

torch.set_num_threads(1)


@pytest.fixture(scope="module")
def split(tmp_path_factory):
    return write_synthetic_split(tmp_path_factory.mktemp("synth") / "train", n_scenes=2,
                                 resolution=32, seed=0)  # fmt: skip


@pytest.fixture(scope="module")
def ds(split):
    return MultiViewDataset(split)


def _one_line(e: pytest.ExceptionInfo) -> str:
    msg = str(e.value)
    assert "\n" not in msg
    return msg


# ----------------------------------------------------------------- reading


def test_shapes_and_dtypes(ds):
    assert len(ds) == 2 and ds.n_views == 4 and ds.image_hw == (32, 32)
    sv = ds[1]
    assert sv.scene == 1
    expect = {
        "images": ((4, 3, 32, 32), torch.float32),
        "K": ((4, 3, 3), torch.float32),
        "cam_to_world": ((4, 4, 4), torch.float32),
        "instances": ((4, 32, 32), torch.int64),
        "depth_z": ((4, 32, 32), torch.float32),
        "rays_o": ((4, 32, 32, 3), torch.float32),
        "rays_d": ((4, 32, 32, 3), torch.float32),
        "z_scale": ((4, 32, 32), torch.float32),
    }
    for name, (shape, dtype) in expect.items():
        x = getattr(sv, name)
        assert tuple(x.shape) == shape and x.dtype == dtype, name
    assert 0.0 <= sv.images.min() and sv.images.max() <= 1.0
    assert sv.instances.min() == 0 and sv.instances.max() >= 1
    assert (sv.instances[:, 0, 0] == 0).all()  # the mask sentinel pixel is background
    torch.testing.assert_close(sv.rays_d.norm(dim=-1), torch.ones(4, 32, 32))
    # Camera centres on the standard rig (radius 12.4).
    torch.testing.assert_close(sv.cam_to_world[:, :3, 3].norm(dim=-1), torch.full((4,), 12.4))
    assert ds.preset == "synthetic"


def test_rays_hit_sphere_at_gt_depth(ds, split):
    """Ray through a sphere centre's pixel: analytic hit t, t * z_scale == depth_z."""
    checked = 0
    for pos, scene in enumerate(ds.scene_ids):
        meta = read_json(SplitLayout(split).scene_json(scene))
        sv = ds[pos]
        for v in range(ds.n_views):
            w2c = torch.linalg.inv(sv.cam_to_world[v].double())
            for obj in meta["objects"]:
                c = torch.tensor(obj["position"], dtype=torch.float64)
                pc = w2c[:3, :3] @ c + w2c[:3, 3]
                uv = sv.K[v].double() @ (pc / pc[2])
                u, vv = math.floor(uv[0]), math.floor(uv[1])
                if not (0 <= u < 32 and 0 <= vv < 32):
                    continue
                if int(sv.instances[v, vv, u]) != obj["instance_id"]:
                    continue  # occluded by another sphere
                o = sv.rays_o[v, vv, u].double()
                d = sv.rays_d[v, vv, u].double()
                oc = o - c
                b = d @ oc
                disc = b * b - (oc @ oc - obj["radius"] ** 2)
                assert disc > 0
                t = -b - torch.sqrt(disc)
                assert float(t * sv.z_scale[v, vv, u]) == pytest.approx(
                    float(sv.depth_z[v, vv, u]), rel=1e-4
                )
                # The pixel centre's ray passes within half a pixel's footprint of the centre.
                miss = torch.linalg.cross(c - o, d).norm()
                assert miss < 0.5 * pc[2] / sv.K[v, 0, 0] * math.sqrt(2) + 1e-6
                checked += 1
    assert checked >= 4


def test_pixel_rays_principal_axis():
    K = torch.tensor([[[40.0, 0, 16], [0, 40.0, 16], [0, 0, 1]]])
    c2w = torch.eye(4)[None]
    _, d, z = pixel_rays(K, c2w, 32, 32)
    # Pixel centres (15.5, 15.5) and (16.5, 16.5) straddle the principal point.
    mid = 0.5 * (d[0, 15, 15] + d[0, 16, 16])
    torch.testing.assert_close(mid / mid.norm(), torch.tensor([0.0, 0.0, 1.0]))
    torch.testing.assert_close(z[0], d[0, ..., 2])
    with pytest.raises(ValueError, match="K must be"):
        pixel_rays(torch.eye(3), c2w, 4, 4)


def test_resize_keeps_intrinsics_consistent(ds, split):
    small = MultiViewDataset(split, image_size=16)
    a, b = ds[0], small[0]
    assert b.images.shape == (4, 3, 16, 16) and small.source_hw == (32, 32)
    S = torch.diag(torch.tensor([0.5, 0.5, 1.0]))
    torch.testing.assert_close(b.K, S @ a.K)
    # Nearest ids: the source pixel under each new pixel centre (2i + 1).
    assert torch.equal(b.instances, a.instances[:, 1::2, 1::2])
    # Area-averaged images (re-quantised to 8 bits).
    avg = a.images.reshape(4, 3, 16, 2, 16, 2).mean(dim=(3, 5))
    assert (b.images - avg).abs().max() <= 0.5 / 255 + 1e-6
    # A point on the small view's pixel-centre ray projects to the matching spot of the
    # original view: pixel centre (u + 0.5) maps to 2 (u + 0.5).
    for v in range(4):
        w2c = torch.linalg.inv(a.cam_to_world[v])
        for y, x in [(0, 0), (5, 11), (15, 15)]:
            p = b.rays_o[v, y, x] + 10.0 * b.rays_d[v, y, x]
            pc = w2c[:3, :3] @ p + w2c[:3, 3]
            uv = a.K[v] @ (pc / pc[2])
            torch.testing.assert_close(uv[:2], torch.tensor([2 * x + 1.0, 2 * y + 1.0]),
                                       atol=1e-3, rtol=0)  # fmt: skip
    with pytest.raises(DatasetError, match="only down-sampling"):
        MultiViewDataset(split, image_size=64)


def test_select_scenes(split):
    one = MultiViewDataset(split, scenes=[1])
    assert one.scene_ids == [1] and len(one) == 1
    with pytest.raises(DatasetError, match="no scene sc0007"):
        MultiViewDataset(split, scenes=[7])
    assert MultiViewDataset(split, max_scenes=1).scene_ids == [0]


def test_uorf_layout_reads_our_folder(ds, split):
    u = MultiViewDataset(split, uorf_layout=True)
    assert u.scene_ids == ds.scene_ids and u.n_views == 4
    a, b = ds[0], u[0]
    assert torch.equal(a.images, b.images)
    torch.testing.assert_close(a.cam_to_world, b.cam_to_world, atol=1e-6, rtol=0)
    # Same partition into instances (the sentinel pixel reads as background).
    assert torch.equal(b.instances == 0, a.instances == 0)
    for k in a.instances.unique():
        assert len(b.instances[a.instances == k].unique()) == 1
    assert torch.isnan(b.depth_z).all()  # no _depth.npy written


def test_invalid_split_errors(tmp_path):
    root = write_synthetic_split(tmp_path / "s", n_scenes=1, resolution=16)
    layout = SplitLayout(root)
    layout.depth(0, 2).unlink()
    with pytest.raises(DatasetError) as e:
        MultiViewDataset(root)
    msg = _one_line(e)
    assert layout.depth(0, 2).name in msg and "generate verify" in msg
    write_synthetic_split(tmp_path / "t", n_scenes=1, resolution=16)
    bad = SplitLayout(tmp_path / "t")
    bad.rgb(0, 1).write_bytes(b"not a png")
    with pytest.raises(DatasetError) as e:
        MultiViewDataset(bad.root)
    assert bad.rgb(0, 1).name in _one_line(e)
    (tmp_path / "empty").mkdir()
    with pytest.raises(DatasetError) as e:
        MultiViewDataset(tmp_path / "empty")
    assert "manifest.json" in _one_line(e)
    with pytest.raises(DatasetError):
        MultiViewDataset(tmp_path / "nope")


def test_fingerprint(tmp_path):
    a = write_synthetic_split(tmp_path / "a", n_scenes=1, resolution=8, seed=1)
    b = write_synthetic_split(tmp_path / "b", n_scenes=1, resolution=8, seed=1)
    c = write_synthetic_split(tmp_path / "c", n_scenes=1, resolution=8, seed=2)
    assert dataset_fingerprint(a) == dataset_fingerprint(b) != dataset_fingerprint(c)
    # Same bytes for masks, depth and JSON on a rewrite (deterministic writer).
    assert SplitLayout(a).depth(0, 0).read_bytes() == SplitLayout(b).depth(0, 0).read_bytes()


# ----------------------------------------------------------------- sampling


def test_sampler_nvs_targets_other_views(ds):
    s = RaySampler(ds, rays_per_scene=48, nvs=True)
    g = torch.Generator().manual_seed(0)
    for _ in range(5):
        b = s.sample(s.sample_scenes(2, g), g)
        assert b.images.shape == (2, 3, 32, 32) and b.rays_d.shape == (2, 48, 3)
        assert (b.target_view != b.input_view[:, None]).all()
        for i, pos in enumerate(b.scenes.tolist()):
            sv = ds[pos]
            assert torch.equal(b.images[i], sv.images[b.input_view[i]])
            y, x = b.target_pixel[i] // 32, b.target_pixel[i] % 32
            tv = b.target_view[i]
            assert torch.equal(b.rays_d[i], sv.rays_d[tv, y, x])
            assert torch.equal(b.rays_o[i], sv.rays_o[tv, y, x])
            # Advanced indices first: [R, 3].
            assert torch.equal(b.target_rgb[i], sv.images[tv, :, y, x])


def test_sampler_without_nvs_uses_input_view(ds):
    s = RaySampler(ds, rays_per_scene=32, nvs=False)
    g = torch.Generator().manual_seed(1)
    b = s.sample(s.sample_scenes(2, g), g)
    assert (b.target_view == b.input_view[:, None]).all()


def test_sampler_deterministic(ds):
    s = RaySampler(ds, rays_per_scene=16, ray_sampling="object_heavy")

    def draw(seed):
        g = torch.Generator().manual_seed(seed)
        return [s.sample(s.sample_scenes(2, g), g) for _ in range(3)]

    for x, y in zip(draw(5), draw(5)):
        for k in x.__dataclass_fields__:
            assert torch.equal(getattr(x, k), getattr(y, k)), k
    assert not torch.equal(draw(5)[0].target_pixel, draw(6)[0].target_pixel)
    with pytest.raises(ValueError, match="unknown ray_sampling"):
        RaySampler(ds, ray_sampling="nope")


def test_object_heavy_fraction(ds):
    assert set(RAY_SAMPLING) >= {"uniform", "object_heavy"}
    s = RaySampler(ds, rays_per_scene=200, ray_sampling="object_heavy")
    g = torch.Generator().manual_seed(0)
    b = s.sample([0, 1], g)
    for i in range(2):
        rgb = ds._rgb[i]  # uint8 [V, H, W, 3]
        # Independent oracle: per-view median colour, any channel off by > 0.1.
        x = rgb.float().numpy() / 255.0
        med = np.median(x.reshape(4, -1, 3), axis=1)[:, None, None, :]
        sal = (np.abs(x - med) > 0.1).any(-1)
        assert 0 < sal.mean() < 0.5
        tv, pix = b.target_view[i].numpy(), b.target_pixel[i].numpy()
        frac = sal[tv, pix // 32, pix % 32].mean()
        assert frac >= 0.5
    # Uniform sampling hits them about as often as they occur.
    u = RaySampler(ds, rays_per_scene=2000, ray_sampling="uniform").sample([0], g)
    tv, pix = u.target_view[0].numpy(), u.target_pixel[0].numpy()
    x = ds._rgb[0].float().numpy() / 255.0
    med = np.median(x.reshape(4, -1, 3), axis=1)[:, None, None, :]
    sal = (np.abs(x - med) > 0.1).any(-1)
    assert sal[tv, pix // 32, pix % 32].mean() < 0.5


def test_object_heavy_flat_image_falls_back_to_uniform():
    flat = torch.full((2, 8, 8, 3), 100, dtype=torch.uint8)
    assert not salient_pixels(flat).any()
    idx = object_heavy_rays(flat, 10, torch.Generator().manual_seed(0))
    assert idx.shape == (10,) and idx.dtype == torch.int64 and (idx < 128).all()
