"""svorf.data: the dataset reader, cached rays, resizing, the ray sampler; svorf.synthetic."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest
import torch

from scenefmt import SplitLayout, read_json
from scenefmt.uorf import uorf_instance_ids
from svorf.data import (
    RAY_SAMPLING,
    DatasetError,
    ErrorMap,
    MultiViewDataset,
    RaySampler,
    dataset_fingerprint,
    pixel_rays,
    rays_at,
    register_ray_sampling,
)
from svorf.synthetic import write_synthetic_split


@pytest.fixture(autouse=True, scope="module")
def _one_thread():
    # The CI/dev boxes have 2 cores shared with other jobs: a second OpenMP thread that
    # waits on a busy core makes tiny steps ~15x slower.
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


@pytest.fixture(scope="module")
def split(tmp_path_factory):
    return write_synthetic_split(
        tmp_path_factory.mktemp("synth") / "train", n_scenes=2, resolution=32, seed=3
    )


@pytest.fixture(scope="module")
def ds(split):
    return MultiViewDataset(split)


def _sphere_t(o: np.ndarray, d: np.ndarray, c: np.ndarray, r: float) -> float:
    """Nearest positive hit distance of a unit ray with a sphere (nan if none)."""
    oc = o - c
    b = float(d @ oc)
    disc = b * b - (float(oc @ oc) - r * r)
    return -b - np.sqrt(disc) if disc >= 0 else float("nan")


def test_shapes_and_dtypes(ds):
    assert len(ds) == 2 and ds.n_views == 4 and ds.image_hw == (32, 32)
    sv = ds[0]
    assert sv.images.shape == (4, 3, 32, 32) and sv.images.dtype == torch.float32
    assert 0.0 <= float(sv.images.min()) and float(sv.images.max()) <= 1.0
    assert sv.K.shape == (4, 3, 3) and sv.cam_to_world.shape == (4, 4, 4)
    assert sv.instances.shape == (4, 32, 32) and sv.instances.dtype == torch.int64
    assert sv.depth_z.shape == (4, 32, 32) and sv.depth_z.dtype == torch.float32
    assert sv.rays_o.shape == sv.rays_d.shape == (4, 32, 32, 3)
    assert sv.z_scale.shape == (4, 32, 32)
    torch.testing.assert_close(sv.rays_d.norm(dim=-1), torch.ones(4, 32, 32))
    assert bool((sv.z_scale > 0).all() and (sv.z_scale <= 1).all())
    # The synthetic plate ends: some rays see no surface (inf), most do.
    assert bool(torch.isinf(sv.depth_z).any()) and bool(torch.isfinite(sv.depth_z).any())
    assert ds.preset == "synthetic" and sv.scene == 0


def test_rays_hit_the_json_spheres_at_the_stored_depth(ds, split):
    """A sphere centre from the JSON projects to a pixel whose ray hits the sphere at
    t with t * z_scale == the stored planar depth (analytic scene)."""
    checked = 0
    for pos in range(len(ds)):
        sv = ds[pos]
        meta = read_json(SplitLayout(split).scene_json(sv.scene))
        for v in range(ds.n_views):
            w2c = torch.linalg.inv(sv.cam_to_world[v].double())
            for obj in meta["objects"]:
                c = torch.tensor(obj["position"], dtype=torch.float64)
                pc = w2c[:3, :3] @ c + w2c[:3, 3]
                uvw = sv.K[v].double() @ pc
                u, vv = int(uvw[0] / uvw[2]), int(uvw[1] / uvw[2])
                if not (0 <= u < 32 and 0 <= vv < 32):
                    continue
                if int(sv.instances[v, vv, u]) != obj["instance_id"]:
                    continue  # occluded by another sphere in this view
                o = sv.rays_o[v, vv, u].double().numpy()
                d = sv.rays_d[v, vv, u].double().numpy()
                t = _sphere_t(o, d, np.asarray(obj["position"]), obj["radius"])
                assert np.isfinite(t)
                got = t * float(sv.z_scale[v, vv, u])
                assert got == pytest.approx(float(sv.depth_z[v, vv, u]), abs=1e-3)
                checked += 1
    assert checked >= 4


def test_resize_keeps_intrinsics_consistent(split, ds):
    small = MultiViewDataset(split, image_size=16)
    assert small.image_hw == (16, 16) and small.source_hw == (32, 32)
    big, sm = ds[1], small[1]
    torch.testing.assert_close(sm.K[:, :2], big.K[:, :2] * 0.5)
    # Pixel (x, y) of the 16x16 image looks through point ((x+.5)*2, (y+.5)*2) of the 32x32 one.
    y, x = torch.meshgrid(torch.arange(16.0), torch.arange(16.0), indexing="ij")
    pix = torch.stack([(x + 0.5) * 2, (y + 0.5) * 2, torch.ones_like(x)], -1).double()
    for v in range(4):
        d_cam = pix @ torch.linalg.inv(big.K[v].double()).T
        d = torch.nn.functional.normalize(d_cam @ big.cam_to_world[v, :3, :3].double().T, dim=-1)
        torch.testing.assert_close(sm.rays_d[v].double(), d, atol=1e-6, rtol=0)
    # Area-averaged colours, nearest ids and depth (the source pixel under the centre).
    blocks = big.images.reshape(4, 3, 16, 2, 16, 2).mean(dim=(3, 5))
    assert float((sm.images - blocks).abs().max()) <= 0.5 / 255 + 1e-6
    assert torch.equal(sm.instances, big.instances[:, 1::2, 1::2])
    assert torch.equal(sm.depth_z, big.depth_z[:, 1::2, 1::2])


def test_sampler_draws_only_target_views(ds):
    g = torch.Generator().manual_seed(0)
    sampler = RaySampler(ds, rays_per_scene=64, nvs=True)
    for _ in range(5):
        b = sampler.sample(sampler.sample_scenes(2, g), g)
        assert b.images.shape == (2, 3, 32, 32)
        assert b.rays_o.shape == b.rays_d.shape == b.target_rgb.shape == (2, 64, 3)
        assert bool((b.target_view != b.input_view[:, None]).all())
        for i, s in enumerate(b.scenes.tolist()):
            sv = ds[s]
            torch.testing.assert_close(b.images[i], sv.images[b.input_view[i]])
            vv, pix = b.target_view[i], b.target_pixel[i]
            yy, xx = pix // 32, pix % 32
            torch.testing.assert_close(b.target_rgb[i], sv.images[vv, :, yy, xx])
            # Computed for the batch's pixels only, bit-identical to the per-image rays.
            assert torch.equal(b.rays_d[i], sv.rays_d[vv, yy, xx])
            assert torch.equal(b.rays_o[i], sv.rays_o[vv, yy, xx])
    same = RaySampler(ds, rays_per_scene=32, nvs=False)
    b = same.sample([0, 1], g)
    assert bool((b.target_view == b.input_view[:, None]).all())
    # TrainConfig.input_view_from: the input view joins the other views as a target.
    many = RaySampler(ds, rays_per_scene=512, nvs=True)
    b = many.sample([0, 1], g, include_input=True)
    for i in range(2):
        views = set(b.target_view[i].tolist())
        assert int(b.input_view[i]) in views and views == set(range(ds.n_views))


def test_sampler_pixel_jitter_moves_rays_inside_their_pixels(ds):
    """TrainConfig.pixel_jitter: the same pixels and target colours as without it, each ray
    through a point of its own pixel (inv(K) @ [u + .5 + du, v + .5 + dv, 1] rotated to the
    world, |du|, |dv| <= side / 2), the points spread over the pixel; side 0 draws nothing."""
    sampler = RaySampler(ds, rays_per_scene=256, nvs=True)
    plain = sampler.sample([0, 1], torch.Generator().manual_seed(3))
    zero = sampler.sample([0, 1], torch.Generator().manual_seed(3), pixel_jitter=0.0)
    for k in plain.__dataclass_fields__:
        assert torch.equal(getattr(zero, k), getattr(plain, k)), k
    for side in (1.0, 0.5):
        b = sampler.sample([0, 1], torch.Generator().manual_seed(3), pixel_jitter=side)
        for k in ("target_rgb", "target_view", "target_pixel", "images", "rays_o"):
            assert torch.equal(getattr(b, k), getattr(plain, k)), k
        assert not torch.equal(b.rays_d, plain.rays_d)
        for i, s in enumerate(b.scenes.tolist()):
            sv = ds[s]
            vv, pix = b.target_view[i], b.target_pixel[i]
            # Back into each view's camera: the ray's point on the image plane.
            rot = sv.cam_to_world[vv, :3, :3].double()
            d_cam = torch.einsum("rji,rj->ri", rot, b.rays_d[i].double())
            uvw = torch.einsum("rij,rj->ri", sv.K[vv].double(), d_cam)
            du = uvw[:, 0] / uvw[:, 2] - (pix % 32).double() - 0.5
            dv = uvw[:, 1] / uvw[:, 2] - (pix // 32).double() - 0.5
            off = torch.stack([du, dv], -1)
            assert float(off.abs().max()) <= side / 2 + 1e-4
            assert float(off.abs().max()) > side / 2 * 0.9  # spread over the square
            assert float(off.abs().mean()) > side / 8


def test_sampler_stride_draws_block_centres_and_block_means(ds):
    """TrainConfig.coarse_to_fine's sampler: each ray through the centre of its stride x
    stride block (the point between the block's pixel centres), its target the block's
    mean colour; stride 1 is the sampler without it."""
    sampler = RaySampler(ds, rays_per_scene=64, nvs=True, ray_sampling="object_heavy")
    plain = sampler.sample([0, 1], torch.Generator().manual_seed(5))
    one = sampler.sample([0, 1], torch.Generator().manual_seed(5), stride=1)
    for k in plain.__dataclass_fields__:
        assert torch.equal(getattr(one, k), getattr(plain, k)), k
    for k in (2, 4):
        b = sampler.sample([0, 1], torch.Generator().manual_seed(5), stride=k)
        assert b.target_rgb.shape == (2, 64, 3)
        assert bool((b.target_view != b.input_view[:, None]).all())
        for i, s in enumerate(b.scenes.tolist()):
            sv = ds[s]
            vv, pix = b.target_view[i], b.target_pixel[i]
            y0, x0 = pix // 32, pix % 32
            assert bool((y0 % k == 0).all() and (x0 % k == 0).all())
            blocks = torch.stack(
                [sv.images[v, :, y : y + k, x : x + k].mean((-1, -2))
                 for v, y, x in zip(vv.tolist(), y0.tolist(), x0.tolist())]
            )  # fmt: skip
            torch.testing.assert_close(b.target_rgb[i], blocks, atol=1e-6, rtol=0)
            # The ray through the block's centre: half-way between its two middle pixels'
            # rays for an even side (the image plane is flat, so the mid-point direction).
            rot = sv.cam_to_world[vv, :3, :3].double()
            d_cam = torch.einsum("rji,rj->ri", rot, b.rays_d[i].double())
            uvw = torch.einsum("rij,rj->ri", sv.K[vv].double(), d_cam)
            torch.testing.assert_close(
                uvw[:, 0] / uvw[:, 2], x0.double() + k / 2, atol=1e-4, rtol=0
            )
            torch.testing.assert_close(
                uvw[:, 1] / uvw[:, 2], y0.double() + k / 2, atol=1e-4, rtol=0
            )
    with pytest.raises(ValueError, match="multiples"):
        sampler.sample([0], torch.Generator(), stride=3)


def test_sampler_input_size_shrinks_only_the_encoder_input(ds):
    """TrainConfig.target_size's sampler: the input view is area-averaged down to
    input_size (what the dataset's own resize would give), the target rays and colours stay
    at the dataset's resolution and are the same draws as without it."""
    small = MultiViewDataset(ds.root, image_size=16)
    fine = RaySampler(ds, rays_per_scene=32, nvs=True, input_size=16)
    plain = RaySampler(ds, rays_per_scene=32, nvs=True)
    a = fine.sample([0, 1], torch.Generator().manual_seed(4))
    b = plain.sample([0, 1], torch.Generator().manual_seed(4))
    assert a.images.shape == (2, 3, 16, 16) and b.images.shape == (2, 3, 32, 32)
    for i, s in enumerate(a.scenes.tolist()):
        want = small[s].images[a.input_view[i]]  # stored as uint8 after its resize
        assert float((a.images[i] - want).abs().max()) <= 0.5 / 255 + 1e-6
    for k in ("rays_o", "rays_d", "target_rgb", "target_pixel", "input_c2w"):
        assert torch.equal(getattr(a, k), getattr(b, k)), k
    assert torch.equal(RaySampler(ds, 8, input_size=32).sample([0], torch.Generator()).images,
                       RaySampler(ds, 8).sample([0], torch.Generator()).images)  # fmt: skip
    with pytest.raises(ValueError, match="input_size"):
        RaySampler(ds, 8, input_size=64)


def test_pixel_rays_equal_the_matrix_form():
    """The element-wise float64 rays equal inv(K) @ [u+.5, v+.5, 1] rotated to the world
    (the matrix form), for a skewed K and a rotation with every entry non-zero."""
    K = torch.tensor([[[40.0, 0.7, 15.5], [0.0, 38.0, 17.25], [0.0, 0.0, 1.0]]])
    a, b, c = 0.3, -0.8, 1.1
    rz = torch.tensor([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1.0]])
    rx = torch.tensor([[1.0, 0, 0], [0, np.cos(b), -np.sin(b)], [0, np.sin(b), np.cos(b)]])
    ry = torch.tensor([[np.cos(c), 0, np.sin(c)], [0, 1.0, 0], [-np.sin(c), 0, np.cos(c)]])
    c2w = torch.eye(4, dtype=torch.float64)[None].clone()
    c2w[0, :3, :3], c2w[0, :3, 3] = rz @ rx @ ry, torch.tensor([1.0, -2.0, 7.0])
    o, d, z = pixel_rays(K, c2w, 6, 5)
    v, u = torch.meshgrid(torch.arange(6.0), torch.arange(5.0), indexing="ij")
    pix = torch.stack([u + 0.5, v + 0.5, torch.ones_like(u)], -1).double()
    d_cam = torch.nn.functional.normalize(pix @ torch.linalg.inv(K[0].double()).T, dim=-1)
    want = d_cam @ c2w[0, :3, :3].T
    torch.testing.assert_close(d[0].double(), want, atol=1e-7, rtol=0)
    torch.testing.assert_close(z[0].double(), d_cam[..., 2], atol=1e-7, rtol=0)
    assert torch.equal(o[0], c2w[0, :3, 3].float())
    # One pixel alone gives the same bits as the whole grid.
    d1, z1 = rays_at(K[0], c2w[0], torch.tensor(3), torch.tensor(4))
    assert torch.equal(d1, d[0, 4, 3]) and torch.equal(z1, z[0, 4, 3])


def test_training_data_without_truth_reads_no_ids_or_depth(split, ds, tmp_path):
    """truth=False (what training loads): the ids and depth files are never read, so a
    split without them loads, and the images, cameras, rays and batches are unchanged."""
    bare = tmp_path / "bare"
    shutil.copytree(split, bare)
    lay = SplitLayout(bare)
    for s in range(2):
        for v in range(4):
            lay.instances(s, v).unlink()
            lay.depth(s, v).unlink()
            lay.mask(s, v).unlink()
    with pytest.raises(DatasetError, match="missing"):
        MultiViewDataset(bare)
    lean = MultiViewDataset(bare, truth=False)
    assert lean._ids is None and lean._depth is None
    sv, full = lean[1], ds[1]
    assert sv.instances is None and sv.depth_z is None
    for k in ("images", "K", "cam_to_world", "rays_o", "rays_d", "z_scale"):
        assert torch.equal(getattr(sv, k), getattr(full, k)), k
    small = MultiViewDataset(bare, image_size=16, truth=False)
    assert torch.equal(small[0].images, MultiViewDataset(split, image_size=16)[0].images)
    g1, g2 = torch.Generator().manual_seed(5), torch.Generator().manual_seed(5)
    b1 = RaySampler(lean, 16, ray_sampling="object_heavy").sample([0, 1], g1)
    b2 = RaySampler(ds, 16, ray_sampling="object_heavy").sample([0, 1], g2)
    for k in b1.__dataclass_fields__:
        assert torch.equal(getattr(b1, k), getattr(b2, k)), k


def test_sampler_is_deterministic_with_the_generator(ds):
    sampler = RaySampler(ds, rays_per_scene=16)

    def draw(seed):
        g = torch.Generator().manual_seed(seed)
        return [sampler.sample(sampler.sample_scenes(2, g), g) for _ in range(3)]

    a, b, c = draw(7), draw(7), draw(8)
    for x, y in zip(a, b):
        assert torch.equal(x.target_pixel, y.target_pixel) and torch.equal(x.rays_d, y.rays_d)
    assert any(not torch.equal(x.target_pixel, z.target_pixel) for x, z in zip(a, c))


def test_sampling_strategy_registry(ds):
    with pytest.raises(ValueError, match="unknown ray_sampling"):
        RaySampler(ds, ray_sampling="nope")
    with pytest.raises(ValueError, match="already registered"):
        register_ray_sampling("uniform", RAY_SAMPLING["uniform"])

    def first_pixels(target_rgb, n, generator):
        return torch.arange(n) % (target_rgb.shape[0] * target_rgb.shape[1] * target_rgb.shape[2])

    register_ray_sampling("test-first", first_pixels)
    try:
        b = RaySampler(ds, 8, ray_sampling="test-first").sample([0], torch.Generator())
        assert b.target_pixel.tolist() == [list(range(8))]
    finally:
        del RAY_SAMPLING["test-first"]


def test_validation_errors_name_the_file(split, tmp_path):
    with pytest.raises(DatasetError, match="not a directory"):
        MultiViewDataset(tmp_path / "nope")
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(DatasetError, match="manifest.json: missing.*generate verify"):
        MultiViewDataset(empty)
    broken = tmp_path / "broken"
    shutil.copytree(split, broken)
    victim = SplitLayout(broken).depth(1, 2)
    victim.unlink()
    with pytest.raises(DatasetError) as e:
        MultiViewDataset(broken)
    msg = str(e.value)
    assert victim.name in msg and "generate verify" in msg and "\n" not in msg
    with pytest.raises(DatasetError, match="only down-sampling"):
        MultiViewDataset(split, image_size=64)
    assert len(MultiViewDataset(split, max_scenes=1)) == 1


def test_fingerprint_tracks_scene_json(split, tmp_path):
    copy = tmp_path / "copy"
    shutil.copytree(split, copy)
    assert dataset_fingerprint(copy) == dataset_fingerprint(split)
    p = SplitLayout(copy).scene_json(0)
    p.write_text(p.read_text().replace('"seed": 3', '"seed": 4'))
    assert dataset_fingerprint(copy) != dataset_fingerprint(split)


def test_uorf_layout_reader(split, ds):
    u = MultiViewDataset(split, uorf_layout=True)
    assert len(u) == 2 and u.n_views == 4
    su, so = u[0], ds[0]
    torch.testing.assert_close(su.images, so.images)
    torch.testing.assert_close(su.cam_to_world, so.cam_to_world)
    assert torch.isnan(su.depth_z).all()  # uORF folders carry no depth
    # uORF rule: background = second-lowest grey; our sentinel pixel (0, 0) is the
    # lowest level and so reads as one extra "object" there, everything else agrees.
    fg_u, fg_o = su.instances > 0, so.instances > 0
    fg_u[:, 0, 0] = False
    assert torch.equal(fg_u, fg_o)
    # Default intrinsics: uORF's focal ratios 350/320 (x) and 350/240 (y).
    torch.testing.assert_close(su.K[0, 0, 0], torch.tensor(350 / 320 * 32.0))
    torch.testing.assert_close(su.K[0, 1, 1], torch.tensor(350 / 240 * 32.0))
    gl = MultiViewDataset(split, uorf_layout=True, uorf_axes="opengl", uorf_fov_deg=40.0)
    flip = torch.diag(torch.tensor([1.0, -1.0, -1.0, 1.0]))
    torch.testing.assert_close(gl[0].cam_to_world, so.cam_to_world @ flip)
    torch.testing.assert_close(gl[0].K[0, 0, 0], gl[0].K[0, 1, 1])


@pytest.mark.parametrize("res", [64, 128, 256])
def test_uorf_ids_read_sentinel_block_and_old_single_pixel_as_background(res):
    """Format 1.1 masks (b x b sentinel block) and format 1.0 ones (pixel (0, 0) only)
    both read back as the instance ids; a low level outside the block stays an object."""
    from scenefmt import MASK_SENTINEL_LEVEL, sentinel_size, uorf_mask_from_instances

    ids = np.zeros((res, res), np.uint8)
    ids[res // 4 : res // 2, res // 3 : res // 2] = 1
    ids[res // 2 :, : res // 3] = 2
    new = uorf_mask_from_instances(ids)
    old = new.copy()
    b = sentinel_size(res, res)
    old[:b, :b] = new[b, b]  # background level
    old[0, 0] = MASK_SENTINEL_LEVEL
    got = uorf_instance_ids([new, old, None], res, res)
    assert got.shape == (3, res, res) and got.dtype == np.uint8
    np.testing.assert_array_equal(got[0], ids)
    np.testing.assert_array_equal(got[1], ids)
    assert not got[2].any()
    # the lowest level reaching past the block is an object (uORF's rule), not a sentinel
    odd = new.copy()
    odd[:b, : b + 1] = MASK_SENTINEL_LEVEL
    assert uorf_instance_ids([odd], res, res)[0][0, b] > 0


def test_synthetic_split_is_deterministic(tmp_path):
    a = write_synthetic_split(tmp_path / "a", n_scenes=1, resolution=16, seed=5)
    b = write_synthetic_split(tmp_path / "b", n_scenes=1, resolution=16, seed=5)
    for name in ("sc0000.json", "00000_sc0000_az00.png", "00003_sc0000_az03_mask.png"):
        assert (a / name).read_bytes() == (b / name).read_bytes()
    manifest = read_json(a / "manifest.json")
    assert manifest["n_scenes"] == 1 and manifest["n_views"] == 4
    assert read_json(a / "sc0000.json")["camera_convention"] == "opencv"


# --------------------------------------------------------------------------- error-driven rays


def test_error_map_draws_in_proportion_to_tile_error():
    em = ErrorMap(3, 4, (10, 12), tile=4, fraction=0.75, ema=0.5)
    assert em.err.shape == (3, 4, 3 * 3)  # ceil(10/4) x ceil(12/4) tiles, partial at the edges
    em.err.fill_(1e-9)
    em.err[1, 2, 5] = 1.0  # view 2, tile row 1, tile col 2 -> y in [4, 8), x in [8, 12)
    views = torch.tensor([0, 2, 3])  # view 2 is candidate position 1
    g = torch.Generator().manual_seed(0)
    flat = em.draw(1, views, 400, g)
    assert flat.shape == (400,) and flat.dtype == torch.int64
    assert int(flat.min()) >= 0 and int(flat.max()) < 3 * 10 * 12
    by_err, rest = flat[:300], flat[300:]
    assert bool((by_err // 120 == 1).all())
    y, x = (by_err % 120) // 12, by_err % 12
    assert bool(((y >= 4) & (y < 8) & (x >= 8) & (x < 12)).all())
    assert len(set((rest // 120).tolist())) == 3  # the uniform share reaches every view
    # the bottom tile row is partial (rows 8..9 of 10): drawn pixels stay in the image
    em.err.fill_(1e-9)
    em.err[0, 0, 7] = 1.0
    flat = em.draw(0, torch.tensor([0]), 200, g)[:150]
    assert int((flat // 12).max()) <= 9 and int((flat // 12).min()) >= 8
    same = em.draw(0, torch.tensor([0]), 200, torch.Generator().manual_seed(5))
    assert torch.equal(same, em.draw(0, torch.tensor([0]), 200, torch.Generator().manual_seed(5)))


def test_error_map_update_blends_the_mean_error_of_each_tile():
    em = ErrorMap(2, 2, (8, 8), tile=4, ema=0.25, init=1.0)
    scenes = torch.tensor([1, 0])
    views = torch.tensor([[1, 1, 0], [0, 0, 0]])
    pixels = torch.tensor([[0, 9, 63], [4, 4, 36]])  # (0,0),(1,1) tile 0; (7,7) tile 3; ...
    err = torch.tensor([[0.2, 0.4, 0.8], [0.6, 1.0, 0.1]])
    em.update(scenes, views, pixels, err)
    expect = torch.ones(2, 2, 4)
    expect[1, 1, 0] = 0.75 + 0.25 * 0.3  # two rays in one tile: their mean
    expect[1, 0, 3] = 0.75 + 0.25 * 0.8
    expect[0, 0, 1] = 0.75 + 0.25 * 0.8  # pixel 4 = (0, 4): tile col 1
    expect[0, 0, 3] = 0.75 + 0.25 * 0.1  # pixel 36 = (4, 4)
    torch.testing.assert_close(em.err, expect)
    em.update(scenes, views, pixels, torch.full((2, 3), float("nan")))  # ignored
    torch.testing.assert_close(em.err, expect)
    other = ErrorMap(2, 2, (8, 8), tile=4)
    other.load_state_dict(em.state_dict())
    assert torch.equal(other.err, em.err)
    with pytest.raises(ValueError, match="does not fit"):
        ErrorMap(3, 2, (8, 8), tile=4).load_state_dict(em.state_dict())
    for bad in ({"tile": 0}, {"fraction": 1.5}, {"ema": 0.0}, {"init": 0.0}):
        with pytest.raises(ValueError, match="ErrorMap"):
            ErrorMap(1, 1, (4, 4), **bad)


def test_error_driven_sampler_shares_one_map_and_stays_in_the_target_views(ds):
    sampler = RaySampler(ds, rays_per_scene=32, nvs=True, ray_sampling="error_driven")
    assert sampler.error_map is not None and "error_driven" in RAY_SAMPLING
    warm = RaySampler(ds, 32, nvs=False, ray_sampling="error_driven", error_map=sampler.error_map)
    assert warm.error_map is sampler.error_map
    assert RaySampler(ds, 32, ray_sampling="object_heavy").error_map is None
    g = torch.Generator().manual_seed(1)
    b = sampler.sample(torch.tensor([0, 1]), g)
    assert bool((b.target_view != b.input_view[:, None]).all())  # novel views only
    w = warm.sample(torch.tensor([1]), g)
    assert bool((w.target_view == w.input_view[:, None]).all())


def test_object_contrast_rays_find_grey_objects_and_stay_label_free():
    """The local-contrast rule marks a grey object on a grey floor (the median rule
    cannot) and ignores a smooth shading ramp; draws are reproducible and in range."""
    from svorf.data import contrast_pixels, object_contrast_rays, salient_pixels

    h = w = 32
    ramp = torch.linspace(90, 140, w).round().to(torch.uint8)  # smooth floor shading
    img = ramp.view(1, 1, w, 1).expand(1, h, w, 3).clone()
    img[0, 10:12, 10:12] = 130  # a small light-grey object, close to the median grey
    assert not salient_pixels(img)[0, 10:12, 10:12].any()  # the median rule misses it
    m = contrast_pixels(img)[0]
    assert m[10:12, 10:12].all()
    assert not m[:, 20:].any() and not m[:5].any()  # the ramp alone is not salient
    g1, g2 = torch.Generator().manual_seed(0), torch.Generator().manual_seed(0)
    a, b = object_contrast_rays(img, 64, g1), object_contrast_rays(img, 64, g2)
    assert torch.equal(a, b) and a.shape == (64,) and int(a.max()) < h * w
    on = m.reshape(-1)[a[:32]]
    assert on.all()  # the salient half comes from salient pixels
    with pytest.raises(ValueError, match="fraction"):
        object_contrast_rays(img, 8, g1, fraction=1.5)


def test_object_heavy_ring_draws_the_floor_ring_beside_a_salient_blob():
    from svorf.ray_sampling import object_heavy_rays

    img = torch.full((1, 12, 12, 3), 100, dtype=torch.uint8)
    img[0, 4:8, 4:8] = torch.tensor([220, 40, 40], dtype=torch.uint8)
    g = torch.Generator().manual_seed(0)
    plain = object_heavy_rays(img, 2000, g, fraction=1.0)
    ring = RAY_SAMPLING["object_heavy_ring"](img, 2000, g, fraction=1.0)
    rows, cols = ring // 12, ring % 12
    assert set((plain // 12).tolist()) == {4, 5, 6, 7}  # the blob alone
    assert rows.min() == 3 and rows.max() == 8 and cols.min() == 3 and cols.max() == 8
    assert len(set(ring.tolist())) == 36  # every pixel of the 6x6 grown blob
    with pytest.raises(ValueError, match="grow"):
        object_heavy_rays(img, 8, g, grow=-1)


def test_edge_and_ring_of_a_square():
    from benchmark.tools.raystats import edge_and_ring

    ids = torch.zeros(1, 6, 6, dtype=torch.long)
    ids[0, 1:4, 1:4] = 2
    edge, ring = edge_and_ring(ids)
    assert int(edge.sum()) == 8 and not edge[0, 2, 2]  # the 3x3's border, not its centre
    assert int(ring.sum()) == 5 * 5 - 9 and ring[0, 0, 0] and not ring[0, 5, 5]


def test_salient_fraction_zero_makes_a_salient_sampler_uniform(split):
    """RaySampler.sample(salient_fraction=...): 0 draws every ray uniformly (the share on
    salient pixels falls to their share of the views), the default keeps half on them;
    a strategy without a salient share refuses it."""
    from svorf.ray_sampling import salient_pixels

    ds = MultiViewDataset(split)
    smp = RaySampler(ds, 256, nvs=False, ray_sampling="object_heavy")

    def on_salient(fraction):
        g = torch.Generator().manual_seed(0)
        hits = []
        for _ in range(8):
            b = smp.sample([0], g, fraction)
            sal = salient_pixels(ds._rgb[0]).reshape(ds.n_views, -1)
            hits.append(sal[b.target_view[0], b.target_pixel[0]].float().mean())
        return float(torch.stack(hits).mean()), float(salient_pixels(ds._rgb[0]).float().mean())

    default, share = on_salient(None)
    uniform, _ = on_salient(0.0)
    assert default > 0.5 + share / 2 - 0.06  # half the rays on salient pixels, plus chance
    assert abs(uniform - share) < 0.06
    with pytest.raises(ValueError, match="salient_fraction"):
        RaySampler(ds, 8, ray_sampling="uniform").sample([0], torch.Generator(), 0.0)


def test_object_balanced_rays_give_a_small_blob_a_large_blobs_share():
    """A 3x3 and a 12x12 object on a uniform floor: object_heavy draws them in proportion
    to area, object_balanced about equally; a speck under min_blob gets a smaller share."""
    from svorf.ray_sampling import blob_weights, object_balanced_rays, object_heavy_rays

    h = w = 32
    img = torch.full((2, h, w, 3), 100, dtype=torch.uint8)
    img[0, 2:14, 2:14] = torch.tensor([200, 30, 30], dtype=torch.uint8)  # large, view 0
    img[1, 20:23, 20:23] = torch.tensor([30, 30, 200], dtype=torch.uint8)  # small, view 1
    img[1, 5, 28] = 250  # a one-pixel highlight
    wts = blob_weights(img, min_blob=4)
    assert wts[0, 2:14, 2:14].sum().item() == pytest.approx(1.0)
    assert wts[1, 20:23, 20:23].sum().item() == pytest.approx(1.0)
    assert wts[1, 5, 28].item() == pytest.approx(0.25)  # 1 pixel of min_blob 4
    assert float(wts.sum()) == pytest.approx(2.25)
    large = torch.zeros(2, h, w, dtype=torch.bool)
    large[0, 2:14, 2:14] = True
    small = torch.zeros(2, h, w, dtype=torch.bool)
    small[1, 20:23, 20:23] = True

    def shares(fn, **kw):
        g = torch.Generator().manual_seed(0)
        idx = torch.cat([fn(img, 400, g, **kw)[:200] for _ in range(20)])  # the salient half
        return large.reshape(-1)[idx].float().mean(), small.reshape(-1)[idx].float().mean()

    big_h, small_h = shares(object_heavy_rays)
    big_b, small_b = shares(object_balanced_rays, min_blob=4)
    assert small_h < 0.1 and big_h > 0.85  # area-weighted: 9 px against 144 px
    assert abs(float(big_b - small_b)) < 0.1 and small_b > 0.35  # blob-weighted
    g1, g2 = torch.Generator().manual_seed(3), torch.Generator().manual_seed(3)
    a, b = object_balanced_rays(img, 64, g1), object_balanced_rays(img, 64, g2)
    assert torch.equal(a, b) and a.shape == (64,) and int(a.max()) < 2 * h * w
    flat = torch.full((1, h, w, 3), 100, dtype=torch.uint8)  # nothing salient: uniform
    assert object_balanced_rays(flat, 16, g1).shape == (16,)
    with pytest.raises(ValueError, match="fraction"):
        object_balanced_rays(img, 8, g1, fraction=-0.1)
    with pytest.raises(ValueError, match="min_blob"):
        blob_weights(img, min_blob=0)
    half = blob_weights(img, min_blob=4, power=0.5)  # a blob's weight: sqrt(area)
    assert half[0].sum().item() == pytest.approx(12.0) and half[
        1, 20:23
    ].sum().item() == pytest.approx(3.0)
    with pytest.raises(ValueError, match="power"):
        blob_weights(img, power=1.5)
    assert "object_balanced" in RAY_SAMPLING and "object_balanced_sqrt" in RAY_SAMPLING


def test_raystats_scores_strategies_against_the_truth(split, tmp_path):
    """Uniform rays land on objects about as often as objects cover the target views."""
    from benchmark.tools.raystats import main, ray_stats

    ds = MultiViewDataset(split)
    ids = ds._ids[:, 1:]
    coverage = float((ids > 0).float().mean())
    r = ray_stats(ds, "uniform", rays=4000, small=1e9)  # every object counts as small
    assert r["rays_on_objects"] == pytest.approx(coverage, abs=0.03)
    assert r["small_objects"] > 0 and r["rays_per_small_object"] > 0
    dense = ray_stats(ds, "uniform", rays=40000)
    assert dense["edge_rate"] == pytest.approx(1.0, abs=0.1)  # uniform: every band alike
    assert dense["ring_rate"] == pytest.approx(1.0, abs=0.1)
    heavy = ray_stats(ds, "object_balanced", rays=4000)
    assert heavy["edge_over_ring"] > 1.5  # the salient half lands on objects, not the ring
    with pytest.raises(ValueError, match="error_driven"):
        ray_stats(ds, "error_driven")
    out = tmp_path / "stats.json"
    assert (
        main(["--data", str(split), "--strategies", "uniform,object_balanced", "--json", str(out)])
        == 0
    )
    assert set(json.loads(out.read_text())["strategies"]) == {"uniform", "object_balanced"}
    assert main(["--data", str(tmp_path / "missing")]) == 2
