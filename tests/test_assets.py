"""Tests for assets_procedural: chairs, textures, background pairs, cache, distinctness.

Fast CPU tests (a few seconds in total); the full 1,200-id distinctness check is
the command ``python -m assets_procedural.distinct --n 1200``.
"""

from __future__ import annotations

import dataclasses
import itertools
import multiprocessing as mp
import os
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import trimesh
from PIL import Image

import assets_procedural as ap
from assets_procedural import _geometry as geo
from assets_procedural import cache as cache_mod
from assets_procedural.chairs import (
    ARM_STYLES,
    BACK_STYLES,
    BASE_KINDS,
    HEIGHT_RANGE,
    LEG_SECTIONS,
    LEG_STYLES,
    SEAT_SHAPES,
    build_chair,
    build_chair_parts,
    chair_mesh,
    chair_params,
)
from assets_procedural.distinct import DESCRIPTOR_NAMES, chair_descriptor, count_distinct
from assets_procedural.textures import (
    FAMILIES,
    FLOOR_FAMILIES,
    N_TEXTURES_DEFAULT,
    WALL_FAMILIES,
    background_params,
    texture_image,
    texture_params,
)

COVERAGE_IDS = range(300)


def _coverage_ids() -> list[int]:
    """First id (in 0..299) for every leg style x back style, arm style, base kind."""
    seen: dict[tuple, int] = {}
    for i in COVERAGE_IDS:
        p = chair_params(i)
        for key in (
            ("lb", p.leg_style, p.back_style),
            ("arm", p.arm_style),
            ("base", p.base_kind if p.leg_style == "pedestal" else None),
            ("seat", p.seat_shape, p.leg_section),
            ("posts", p.rear_posts_from_legs),
            ("stretch", p.stretchers),
        ):
            seen.setdefault(key, i)
    return sorted(set(seen.values()))


# --------------------------------------------------------------------------- geometry


def test_sweep_box_is_exact_closed_solid():
    v, f = geo.box((1.0, 2.0, 3.0), (2.0, 3.0, 4.0))
    m = trimesh.Trimesh(v, f, process=False)
    assert m.is_watertight and m.is_winding_consistent
    assert m.volume == pytest.approx(24.0, rel=1e-12)
    np.testing.assert_allclose(m.bounds, [[0, 0.5, 1], [2, 3.5, 5]], atol=1e-12)


def test_sweep_bent_tube_and_closed_ring():
    prof = geo.circle_profile(0.05, 8)
    poly_area = 0.5 * 8 * 0.05**2 * np.sin(2 * np.pi / 8)
    v, f = geo.tube((0, 0, 0), (0, 0, 2), prof)
    assert geo.signed_volume(v, f) == pytest.approx(2 * poly_area, rel=1e-12)
    path = geo.round_corners(np.array([[0, 0, 1.0], [0, 0, 0], [1, 0, 0], [1, 0, 1]]), 0.2, 4)
    for v, f in (
        geo.sweep(path, geo.rect_profile(0.1, 0.1)),
        geo.sweep(
            np.array([[np.cos(a), np.sin(a), 0] for a in np.linspace(0, 6, 12)]), prof, closed=True
        ),
    ):
        m = trimesh.Trimesh(v, f, process=False)
        assert m.is_watertight and m.is_winding_consistent and m.volume > 0
    with pytest.raises(ValueError, match="coincident"):
        geo.sweep(np.array([[0, 0, 0], [0, 0, 0.0]]), prof)


# --------------------------------------------------------------------------- chairs


def test_chair_determinism_and_ids_differ():
    a, b = chair_mesh(7), chair_mesh(7)
    assert np.array_equal(a.vertices, b.vertices) and np.array_equal(a.faces, b.faces)
    assert chair_params(7) == chair_params(np.int64(7))
    meshes = [chair_mesh(i) for i in range(20)]
    for (i, m), (j, n) in itertools.combinations(enumerate(meshes), 2):
        same = m.vertices.shape == n.vertices.shape and np.allclose(m.vertices, n.vertices)
        assert not same, f"chairs {i} and {j} are identical"


def test_chair_bad_ids():
    for bad, exc in ((-1, ValueError), (1.5, TypeError), (True, TypeError), ("3", TypeError)):
        with pytest.raises(exc, match="asset_id"):
            chair_params(bad)
    with pytest.raises(TypeError, match="ChairParams"):
        build_chair({"asset_id": 1})
    p = chair_params(1)
    with pytest.raises(ValueError, match="leg_style"):
        dataclasses.replace(p, leg_style="tripod")
    with pytest.raises(ValueError, match="seat_width"):
        dataclasses.replace(p, seat_width=0.0)
    # Hand-made variations build fine.
    m = build_chair(dataclasses.replace(p, back_style="ladder", back_count=3, back_height=0.4))
    assert m.bounds[0][2] == 0.0


@pytest.mark.parametrize("asset_id", list(range(60)) + [1047, 1161, 123456789])
def test_chair_canonical_frame(asset_id):
    m = chair_mesh(asset_id)
    lo, hi = m.bounds
    assert lo[2] == 0.0  # rests exactly on the floor
    assert max(hi[0] - lo[0], hi[1] - lo[1]) == pytest.approx(1.0, abs=1e-12)
    assert abs(lo[0] + hi[0]) < 1e-12 and abs(lo[1] + hi[1]) < 1e-12  # footprint centred
    assert HEIGHT_RANGE[0] <= hi[2] - lo[2] <= HEIGHT_RANGE[1]
    assert m.vertices.dtype == np.float64 and m.faces.dtype == np.int64
    md = m.metadata
    assert md["asset_id"] == asset_id and sum(md["part_face_counts"]) == len(m.faces)
    assert 0.2 < md["metres_per_unit"] < 1.2
    # Front faces -y: back rest parts lie behind (+y of) the seat centre.
    p = chair_params(asset_id)
    parts = build_chair_parts(p)
    seat = parts[0]
    assert seat.name == "seat"
    back = [pt for pt in parts if pt.name in ("back", "slat", "rail")]
    assert bool(back) == (not p.is_stool)
    if back:
        assert np.mean([pt.vertices[:, 1].mean() for pt in back]) > seat.vertices[:, 1].mean()
        assert max(pt.vertices[:, 2].max() for pt in back) > seat.vertices[:, 2].max()


def test_every_part_closed_and_outward():
    ids = sorted(set(range(30)) | set(_coverage_ids()))
    for i in ids:
        parts = build_chair_parts(chair_params(i))
        whole = build_chair(chair_params(i))
        assert whole.volume == pytest.approx(
            sum(geo.signed_volume(p.vertices, p.faces) for p in parts)
        )
        for pt in parts:
            m = trimesh.Trimesh(pt.vertices, pt.faces, process=False)
            assert m.is_watertight, (i, pt.name)
            assert m.is_winding_consistent, (i, pt.name)
            assert m.volume > 0, (i, pt.name)
        # Concatenation keeps parts apart: one connected component per part.
        assert len(whole.split(only_watertight=False)) == len(parts)


def test_parameter_coverage_over_300_ids():
    ps = [chair_params(i) for i in COVERAGE_IDS]
    assert {p.leg_style for p in ps} == set(LEG_STYLES)
    assert {p.back_style for p in ps} == set(BACK_STYLES)
    assert {p.arm_style for p in ps} == set(ARM_STYLES)
    assert {p.seat_shape for p in ps} == set(SEAT_SHAPES)
    assert {p.leg_section for p in ps} == set(LEG_SECTIONS)
    assert {p.base_kind for p in ps if p.leg_style == "pedestal"} == set(BASE_KINDS)
    stools = [p for p in ps if p.is_stool]
    assert len(stools) >= 20 and any(p.seat_height > 0.6 for p in stools)
    assert {p.back_count for p in ps if p.back_style == "slats"} >= {2, 7}
    assert any(p.rear_posts_from_legs for p in ps) and any(p.seat_taper < 1 for p in ps)
    for p in ps:  # plain JSON-able scalars
        assert all(isinstance(v, (int, float, str, bool)) for v in p.to_dict().values())


# --------------------------------------------------------------------------- textures


def test_texture_determinism_dtype_shape():
    for tid in range(len(FAMILIES)):
        a, b = texture_image(tid, 64), texture_image(tid, 64)
        assert a.dtype == np.uint8 and a.shape == (64, 64, 3)
        assert np.array_equal(a, b)
        assert a.std() > 0.5  # not a flat colour
    assert texture_image(3).shape == (256, 256, 3)
    assert [texture_params(t).family for t in range(8)] == list(FAMILIES)
    with pytest.raises(ValueError, match="texture_id"):
        texture_image(-2)
    with pytest.raises(ValueError, match="size"):
        texture_image(1, 4)


def test_fifty_textures_pairwise_distinct_and_fast():
    texture_image(3, 32)  # warm up lazy imports (scipy KD-tree)
    t0 = time.perf_counter()
    imgs = [texture_image(t, 256).astype(np.float32) for t in range(N_TEXTURES_DEFAULT)]
    per_texture = (time.perf_counter() - t0) / N_TEXTURES_DEFAULT
    assert per_texture < 0.2, f"{per_texture:.3f} s per 256x256 texture"
    for i, j in itertools.combinations(range(len(imgs)), 2):
        assert np.abs(imgs[i] - imgs[j]).mean() > 3.0, (i, j)
    # Periodic families tile: the wrap-around seam is no stronger than the interior.
    for t in (1, 3, 5, 7):
        im = imgs[t]
        seam = np.abs(im[:, 0] - im[:, -1]).mean()
        interior = np.abs(np.diff(im, axis=1)).mean()
        assert seam < 4 * interior + 8, (t, seam, interior)


def test_background_pairs():
    pairs = [background_params(b) for b in range(N_TEXTURES_DEFAULT)]
    assert len(set(pairs)) == N_TEXTURES_DEFAULT
    used = {t for pair in pairs for t in pair}
    assert used == set(range(N_TEXTURES_DEFAULT))
    for f, w in pairs:
        ff, wf = texture_params(f).family, texture_params(w).family
        assert ff in FLOOR_FAMILIES and wf in WALL_FAMILIES and ff != wf
    assert background_params(17) == pairs[17]
    with pytest.raises(ValueError, match="bg_id"):
        background_params(10_000)


# --------------------------------------------------------------------------- cache


def test_cache_writes_once_and_round_trips(tmp_path, monkeypatch):
    calls = []
    real = cache_mod.chair_mesh
    monkeypatch.setattr(cache_mod, "chair_mesh", lambda i: calls.append(i) or real(i))
    p1 = ap.cached_chair_path(11, tmp_path)
    st = p1.stat()
    p2 = ap.cached_chair_path(11, tmp_path)
    assert p1 == p2 and calls == [11] and p2.stat().st_mtime_ns == st.st_mtime_ns
    assert ap.CHAIR_GENERATOR_VERSION in p1.name
    loaded = ap.load_cached_chair(11, tmp_path)
    ref = chair_mesh(11)
    assert np.array_equal(loaded.faces, ref.faces)
    np.testing.assert_allclose(loaded.vertices, ref.vertices, atol=1e-6)  # PLY float32

    t = ap.cached_texture_path(4, 32, tmp_path)
    assert t.suffix == ".png" and ap.cached_texture_path(4, 32, tmp_path) == t
    assert np.array_equal(np.asarray(Image.open(t)), texture_image(4, 32))
    assert not list(tmp_path.rglob("*.tmp"))


def test_cache_dir_from_env(tmp_path, monkeypatch):
    monkeypatch.setenv("SVORF_ASSET_CACHE", str(tmp_path / "envcache"))
    p = ap.cached_texture_path(0, 16)
    assert p.is_file() and p.is_relative_to(tmp_path / "envcache")
    monkeypatch.delenv("SVORF_ASSET_CACHE")
    assert ap.default_cache_dir() == Path("~/.cache/svorf/assets").expanduser()


def test_cache_concurrent_threads(tmp_path):
    n = 8
    barrier = threading.Barrier(n)
    out: list[Path] = []

    def worker():
        barrier.wait()
        out.append(ap.cached_chair_path(42, tmp_path))

    threads = [threading.Thread(target=worker) for _ in range(n)]
    for th in threads:
        th.start()
    for th in threads:
        th.join()
    assert len(set(out)) == 1 and len(out) == n
    files = [p for p in tmp_path.rglob("*") if p.is_file()]
    assert files == [out[0]]
    m = trimesh.load(out[0], process=False)
    assert len(m.faces) == len(chair_mesh(42).faces)


def _proc_worker(args):
    cache_dir, barrier = args
    barrier.wait()
    return str(ap.cached_texture_path(9, 128, cache_dir)), str(ap.cached_chair_path(9, cache_dir))


@pytest.mark.skipif(sys.platform == "win32", reason="uses the fork start method")
def test_cache_concurrent_processes(tmp_path):
    ctx = mp.get_context("fork")
    n = 3
    barrier = ctx.Barrier(n)
    procs_out = ctx.Queue()

    def run():
        procs_out.put(_proc_worker((tmp_path, barrier)))

    procs = [ctx.Process(target=run) for _ in range(n)]
    for p in procs:
        p.start()
    results = [procs_out.get(timeout=60) for _ in range(n)]
    for p in procs:
        p.join(timeout=60)
        assert p.exitcode == 0
    assert len(set(results)) == 1
    files = sorted(p for p in tmp_path.rglob("*") if p.is_file())
    assert [str(f) for f in files] == sorted(results[0])
    assert np.array_equal(np.asarray(Image.open(results[0][0])), texture_image(9, 128))
    assert len(trimesh.load(results[0][1], process=False).faces) == len(chair_mesh(9).faces)


# --------------------------------------------------------------------------- distinctness


def test_descriptor_shape_and_equal_meshes():
    d = chair_descriptor(chair_mesh(3))
    assert d.shape == (len(DESCRIPTOR_NAMES),) and np.all(np.isfinite(d))
    assert d[DESCRIPTOR_NAMES.index("n_parts")] == len(build_chair_parts(chair_params(3)))
    assert d[DESCRIPTOR_NAMES.index("extent_z")] == pytest.approx(chair_mesh(3).extents[2])
    hist = d[[n.startswith("area_hist") for n in DESCRIPTOR_NAMES]]
    assert hist.sum() == pytest.approx(1.0)
    n, det = count_distinct([3, 5, 3])
    assert n == 2 and det.groups == [[3, 3]] and det.min_distance == 0.0


def test_200_ids_distinct():
    n, det = count_distinct(range(200))
    assert n == 200, det.groups
    assert det.min_distance > det.tol


def test_distinct_cli(capsys):
    from assets_procedural.distinct import main

    assert main(["--n", "12", "--start", "100"]) == 0
    line = capsys.readouterr().out.splitlines()[0]
    assert line.startswith("12 chair ids -> 12 geometrically distinct meshes")


def test_no_torch_or_bpy_import():
    code = (
        "import sys, assets_procedural, assets_procedural.distinct;"
        "bad = [m for m in ('torch', 'bpy') if m in sys.modules];"
        "print(bad); sys.exit(1 if bad else 0)"
    )
    env = dict(os.environ, PYTHONPATH=str(Path(__file__).resolve().parents[1]))
    res = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, env=env, check=False
    )
    assert res.returncode == 0, res.stdout + res.stderr
