"""``python -m benchmark.tools.compare``: two recipe arms side by side at each seed."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from benchmark.tools.compare import CompareError, compare_arms, lower_is_better, main, read_arm

FP = {0: "a" * 64, 1: "b" * 64}


def _report(folder: Path, protocol: str, seed: int, metrics: dict, decomposes: bool = True,
            fingerprint: str | None = None, steps: int = 25000) -> Path:  # fmt: skip
    folder.mkdir(parents=True)
    row = {"source": "measured", "dataset": "clevr567", "variant": "full", "model": "sVORF",
           "run_key": f"k{seed}", "metrics": metrics, "test_dataset": "clevr567/test",
           "test_fingerprint": fingerprint or FP[seed]}  # fmt: skip
    paper = {
        "source": "paper",
        "dataset": "clevr567",
        "variant": "full",
        "metrics": {"fg_ari": 92.0},
    }
    verdicts = [{"dataset": "clevr567", "model": "sVORF", "decomposes": decomposes}]
    report = {"kind": "svorf-benchmark-report", "protocol": protocol, "seeds": {"train": seed},
              "rows": [paper, row], "verdicts": verdicts if protocol == "segmentation" else [],
              "models": [{"run_key": f"k{seed}", "steps_done": str(steps)}]}  # fmt: skip
    (folder / "report.json").write_text(json.dumps(report))
    return folder


def _diagnose(path: Path, fg_ari: float, lost: float, split: int) -> Path:
    path.write_text(json.dumps({"lost": {"fraction": lost}, "merged": {"fraction": 0.02},
                                "own": {"fraction": 1 - lost - 0.02}, "splits": {"split": split},
                                "fg_ari_repairs": {"fg_ari": fg_ari / 100}}))  # fmt: skip
    return path


def test_deltas_means_and_direction_at_two_seeds(tmp_path):
    w = [_report(tmp_path / f"w{s}", "segmentation", s, {"fg_ari": 84.0 + s, "ari": 75.0})
         for s in (0, 1)]  # fmt: skip
    w += [
        _report(tmp_path / f"wn{s}", "nvs", s, {"psnr": 31.8, "depth_abs_rel": 0.05})
        for s in (0, 1)
    ]
    o = [_report(tmp_path / f"o{s}", "segmentation", s, {"fg_ari": 83.0, "ari": 75.0 + s})
         for s in (0, 1)]  # fmt: skip
    o += [
        _report(tmp_path / f"on{s}", "nvs", s, {"psnr": 31.5, "depth_abs_rel": 0.07})
        for s in (0, 1)
    ]
    res = compare_arms(read_arm(w), read_arm(o))
    assert res["seeds"] == [0, 1]
    fg = res["metrics"]["segmentation.fg_ari"]
    assert fg["delta"] == {0: pytest.approx(1.0), 1: pytest.approx(2.0)}
    assert fg["mean_delta"] == pytest.approx(1.5) and fg["better_at_every_seed"]
    ari = res["metrics"]["segmentation.ari"]
    assert ari["delta"] == {0: 0.0, 1: -1.0} and not ari["better_at_every_seed"]  # a tie is no win
    depth = res["metrics"]["nvs.depth_abs_rel"]
    assert depth["better"] == "lower" and depth["better_at_every_seed"]
    assert res["decomposes"] == {"with": {0: True, 1: True}, "without": {0: True, 1: True}}
    assert res["steps"]["with"] == {0: 25000, 1: 25000}
    assert lower_is_better("nvs.lpips") and not lower_is_better("nvs.psnr")


def test_refuses_different_scenes_and_unpaired_seeds(tmp_path):
    w = read_arm([_report(tmp_path / "w0", "segmentation", 0, {"fg_ari": 80.0})])
    o = read_arm(
        [_report(tmp_path / "o0", "segmentation", 0, {"fg_ari": 80.0}, fingerprint="c" * 64)]
    )
    with pytest.raises(CompareError, match="different clevr567/test scenes"):
        compare_arms(w, o)
    assert compare_arms(w, o, allow_different_scenes=True)["metrics"]["segmentation.fg_ari"]
    o1 = read_arm([_report(tmp_path / "o1", "segmentation", 1, {"fg_ari": 80.0})])
    with pytest.raises(CompareError, match="different seeds"):
        compare_arms(w, o1)


def test_diagnose_must_match_its_seeds_model(tmp_path, capsys):
    w = _report(tmp_path / "w0", "segmentation", 0, {"fg_ari": 82.0})
    _diagnose(w / "diagnose.json", 82.0, 0.2, 30)  # picked up from the folder
    o = _report(tmp_path / "o0", "segmentation", 0, {"fg_ari": 83.0})
    good = _diagnose(tmp_path / "good.json", 83.0, 0.25, 22)
    bad = _diagnose(tmp_path / "bad.json", 79.0, 0.25, 22)
    out = tmp_path / "cmp.json"
    assert main(["--with", str(w), "--without", str(o), "--diagnose-without", f"0={good}",
                 "--json", str(out)]) == 0  # fmt: skip
    text = capsys.readouterr().out
    assert "diagnose.lost" in text and "20.0% / 25.0% (-5.0%)" in text
    saved = json.loads(out.read_text())
    assert saved["metrics"]["diagnose.split"]["delta"] == {"0": 8}
    assert main(["--with", str(w), "--without", str(o), "--diagnose-without", f"0={bad}"]) == 2
    assert "diagnosed another model" in capsys.readouterr().err
    assert main(["--with", str(w), "--without", str(o), "--diagnose-without", str(good)]) == 2
    assert "expected SEED=FILE" in capsys.readouterr().err
    (tmp_path / "broken.json").write_text("{")
    assert main(["--with", str(w), "--without", str(o), "--diagnose-without",
                 f"0={tmp_path / 'broken.json'}"]) == 2  # fmt: skip
    assert "not JSON" in capsys.readouterr().err


def test_one_line_errors_for_bad_folders(tmp_path, capsys):
    assert main(["--with", str(tmp_path / "nope"), "--without", str(tmp_path)]) == 2
    err = capsys.readouterr().err.strip()
    assert "no report.json" in err and len(err.splitlines()) == 1
    (tmp_path / "x").mkdir()
    (tmp_path / "x" / "report.json").write_text("{")
    assert main(["--with", str(tmp_path / "x"), "--without", str(tmp_path / "x")]) == 2
    assert "not JSON" in capsys.readouterr().err
