"""Atomic writers give files the mode a plain open() gives (0o666 & ~umask), not 0600."""

from __future__ import annotations

import os
import stat

import numpy as np
import pytest

import scenefmt
from scenefmt import io as sio


@pytest.fixture
def umask():
    """Set the process umask for one test (and forget the cached one around it)."""
    old = os.umask(0o022)
    os.umask(old)

    def set_(mask: int) -> None:
        os.umask(mask)
        sio.reset_file_mode_cache()

    yield set_
    os.umask(old)
    sio.reset_file_mode_cache()


def _mode(path) -> int:
    return stat.S_IMODE(os.stat(path).st_mode)


@pytest.mark.parametrize("mask", [0o022, 0o002, 0o077])
def test_default_file_mode_follows_the_umask(umask, mask, tmp_path):
    umask(mask)
    assert scenefmt.default_file_mode() == 0o666 & ~mask
    with open(tmp_path / "plain", "w"):
        pass
    assert scenefmt.default_file_mode() == _mode(tmp_path / "plain")
    assert os.umask(mask) == mask  # reading it left the umask as it was


def test_umask_fallback_without_proc(umask, monkeypatch):
    umask(0o027)
    real_open = open

    def no_proc(path, *a, **k):
        if str(path) == "/proc/self/status":
            raise OSError("no /proc")
        return real_open(path, *a, **k)

    monkeypatch.setattr("builtins.open", no_proc)
    assert sio._read_umask() == 0o027
    assert os.umask(0o027) == 0o027


def test_dataset_files_get_0644_under_umask_022(umask, tmp_path):
    umask(0o022)
    scenefmt.atomic_write_json(tmp_path / "sc0000.json", {"a": 1})
    scenefmt.write_rgb(tmp_path / "x.png", np.zeros((4, 4, 3), np.uint8))
    scenefmt.write_instances(tmp_path / "i.png", np.zeros((4, 4), np.uint8))
    scenefmt.write_matrix_txt(tmp_path / "m.txt", np.eye(4))
    scenefmt.write_depth_exr(tmp_path / "d.exr", np.ones((4, 4), np.float32))
    names = ["sc0000.json", "x.png", "i.png", "m.txt", "d.exr"]
    assert {n: oct(_mode(tmp_path / n)) for n in names} == {n: "0o644" for n in names}
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(names)  # no temp files left


def test_checkpoint_report_and_cache_files_get_0644_under_umask_022(umask, tmp_path):
    umask(0o022)
    from assets_procedural.cache import atomic_write_bytes as cache_write
    from benchmark.report import write_json
    from benchmark.tools.speedbench import _write_json_atomic
    from svorf.checkpoint import atomic_torch_save

    atomic_torch_save({"x": 1}, tmp_path / "checkpoint.pt")
    write_json(tmp_path / "report.json", {"ok": True})
    _write_json_atomic(tmp_path / "speed.json", {"ok": True})
    cache_write(tmp_path / "chair.ply", b"ply\n")
    names = ["checkpoint.pt", "report.json", "speed.json", "chair.ply"]
    assert {n: oct(_mode(tmp_path / n)) for n in names} == {n: "0o644" for n in names}


def test_mkstemp_beside_is_hidden_and_has_the_default_mode(umask, tmp_path):
    umask(0o002)
    fd, tmp = scenefmt.mkstemp_beside(tmp_path / "out.json")
    os.close(fd)
    assert tmp.parent == tmp_path and tmp.name.startswith(".out.json.")
    assert _mode(tmp) == 0o664
