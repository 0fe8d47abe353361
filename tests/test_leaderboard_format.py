"""The printed leaderboard and the HTML page read the way the paper does.

Fast tier: a set of hand-made, schema-valid reports (segmentation with every segmentation
metric, nvs, speed, stability with long case names, a failed row, an invalid report);
nothing trains. Checks: every printed line fits 120 columns, numbers follow the paper's
conventions (ARI family 0-100 with one decimal, PSNR in dB, SSIM / LPIPS three decimals,
times with units), titles are words, null reasons are words, and report.json keeps its
stored values.
"""

from __future__ import annotations

import json
import re

from benchmark.html import render_html
from benchmark.leaderboard import WIDTH, format_leaderboard, merge_reports
from benchmark.paper_numbers import paper_rows
from benchmark.report import new_report, write_report

SEG = {
    "nv_ari": -3.8512,
    "ari": 0.30841,
    "fg_ari": 19.4912,
    "nv_fg_ari": 10.2634,
    "ari_all": -1.2801,
    "fg_ari_all": 11.3911,
    "ari_shuffled": 0.99741,
    "fg_ari_shuffled": 23.5712,
    "fg_ari_gain": -4.08,
    "depth_abs_rel": 0.19751,
}


def _row(table, model, dataset, source, metrics, reasons=None, **extra):
    return {
        "id": f"{table}|{model}|{dataset}|{source}",
        "table": table,
        "model": model,
        "dataset": dataset,
        "variant": None,
        "source": source,
        "metrics": metrics,
        "null_reasons": reasons or {},
        "n_scenes": 4,
        **extra,
    }


def _report(protocol, rows, created="2025-01-01T00:00:00Z", seed=0):
    rep = new_report(protocol, "smoke", "cpu")
    rep["created_utc"] = created
    rep["seeds"]["train"] = seed
    rep["rows"] = rows
    return rep


def _write_set(root):
    seg = paper_rows("tab:seg")
    for ds in ("clevr567", "room-chair", "room-diverse"):
        seg.append(_row("tab:seg", "sVORF", ds, "measured", dict(SEG)))
        seg.append(
            _row(
                "tab:seg",
                "chance: uniform random slot per pixel",
                ds,
                "baseline",
                {k: 0.0290 for k in ("nv_ari", "ari", "fg_ari", "nv_fg_ari", "ari_all")},
            )
        )
    write_report(root / "segmentation-smoke" / "report.json", _report("segmentation", seg))
    # a second training seed of the same protocol: a separate entry
    seg1 = [dict(r, metrics=dict(r["metrics"])) for r in seg]
    write_report(
        root / "segmentation-smoke-seed1" / "report.json", _report("segmentation", seg1, seed=1)
    )
    nvs = paper_rows("tab:nvs") + [
        _row(
            "tab:nvs",
            "sVORF",
            "clevr567",
            "measured",
            {"lpips": None, "ssim": 0.70114, "psnr": 21.4712, "depth_rmse": 1.2345},
            {"lpips": "lpips_unavailable"},
        ),
        _row(
            "tab:nvs",
            "chance: flat median colour of the input view",
            "clevr567",
            "baseline",
            {"lpips": 0.51234, "ssim": 0.61234, "psnr": 18.04},
        ),
        _row(
            "tab:nvs",
            "sVORF",
            "room-chair",
            "measured",
            {"lpips": None, "ssim": None, "psnr": None},
            {k: "failed: RuntimeError: " + "x" * 280 for k in ("lpips", "ssim", "psnr")},
            failed="RuntimeError",
        ),
    ]
    write_report(root / "nvs-smoke" / "report.json", _report("nvs", nvs))
    speed = paper_rows("tab:time") + [
        _row(
            "tab:time",
            "sVORF",
            "clevr567",
            "measured",
            {
                "memory_gb": 0.391,
                "epoch_time_s": 1050.0,
                "steps_per_s": 12.345,
                "step_time_s": 0.081,
                "peak_memory_mb": 400.4,
                "render_s_per_view": 1.234,
            },
        )
    ]
    write_report(root / "speed-smoke" / "report.json", _report("speed", speed))
    stab = [
        _row(
            "stability",
            f"stress case {i}: densities 0..1e38 and inf with spacings 1e-8..1e6, autocast bf16",
            "synthetic inputs",
            "measured",
            {
                "max_abs_err_rgb": 2.04e-7,
                "max_abs_err_depth": 0.0,
                "max_rel_err_depth": 1.1e-9,
                "max_abs_err_acc": 3.3e-8,
                "nonfinite_count": 0,
                "max_abs_err_m": 1e-7,
                "max_rel_err": 2e-9,
                "error": 0.0,
                "time_s": 0.0021,
            },
            passed=True,
        )
        for i in range(2)
    ]
    write_report(root / "stability-smoke" / "report.json", _report("stability", stab))
    (root / "broken").mkdir()
    (root / "broken" / "report.json").write_text(
        json.dumps({"schema_version": "0", "x": "y" * 400})
    )


def test_printed_leaderboard_fits_120_columns_and_reads_like_the_paper(tmp_path):
    _write_set(tmp_path)
    before = {p: p.read_text() for p in tmp_path.rglob("report.json")}
    board = merge_reports(tmp_path)
    text = format_leaderboard(board)
    lines = text.splitlines()
    too_wide = [line for line in lines if len(line) > WIDTH]
    assert not too_wide, too_wide
    assert WIDTH == 120
    # Titles are words with the paper's table numbers; no LaTeX labels as titles.
    for title in (
        "Segmentation (Table 1)",
        "Novel view synthesis (Table 3)",
        "Memory and training time (Table 8)",
    ):
        assert f"== {title} ==" in lines
    assert not any(line.startswith("== tab:") for line in lines)
    # The ARI family on the 0-100 scale, one decimal; the paper's own numbers too.
    assert "0-100 scale" in text
    seg = next(line for line in lines if line.startswith("sVORF ") and "seed 0" in line)
    assert re.search(r"\s-3\.9\s+0\.3\s+19\.5\s", seg), seg
    assert re.search(r"\s81\.5\s+82\.7\s+92\.0", text)
    assert "0.3084" not in text and "19.49" not in text
    # PSNR in dB with one decimal; SSIM / LPIPS three decimals; times and memory with units.
    assert "21.5 dB" in text and "0.701" in text and "0.512" in text and "37.2 dB" in text
    assert "17.5 min" in text and "81.0 ms" in text and "0.39 GB" in text and "204 s" in text
    assert "2.0e-07" in text
    # Measured rows of two seeds are separate entries.
    assert any("smoke seed 1" in line for line in lines)
    # Null reasons are words; codes are not printed.
    assert "not in the paper" in text and "paper_na" not in text
    assert "LPIPS weights not available" in text and "lpips_unavailable" not in text
    assert "row failed: RuntimeError" in text
    # Columns that do not fit continue in a second part, rows keep their model name.
    assert "(part 2 of 2 of the columns)" in text
    # Skipped reports are listed, wrapped.
    assert "Skipped reports:" in text and "broken" in text
    # report.json is not rewritten; leaderboard.json keeps the stored values.
    assert {p: p.read_text() for p in tmp_path.rglob("report.json")} == before
    stored = json.loads((tmp_path / "leaderboard.json").read_text())
    sv = next(e for e in stored["entries"] if e["source"] == "measured" and e["table"] == "tab:seg")
    assert sv["metrics"]["ari"] == SEG["ari"] and sv["metrics"]["fg_ari"] == SEG["fg_ari"]


def test_narrower_terminals_split_the_columns(tmp_path):
    _write_set(tmp_path)
    text = format_leaderboard(merge_reports(tmp_path, write=False), width=80)
    assert all(len(line) <= 80 for line in text.splitlines())


def test_html_page_uses_the_same_formats(tmp_path):
    _write_set(tmp_path)
    rep = json.loads((tmp_path / "segmentation-smoke" / "report.json").read_text())
    rep["verdicts"] = [
        {
            "table": "tab:seg",
            "dataset": "clevr567",
            "model": "sVORF",
            "decomposes": False,
            "fg_ari": 19.4912,
            "chance_fg_ari": 80.6534,
            "fg_ari_shuffled": 23.5712,
            "message": "does NOT decompose",
        }
    ]
    page = render_html(rep)
    assert "<h2>Segmentation (Table 1)</h2>" in page and "<h2>tab:seg</h2>" not in page
    assert "<td title=''>19.5</td>" in page and "<td>80.7</td>" in page
    assert ">FG-ARI shuffled</th>" in page and "title='fg_ari_shuffled in report.json" in page
    assert "NV-ARI: not in the paper" in page and "paper_na" not in page
    assert "0-100 scale" in page
    nvs = json.loads((tmp_path / "nvs-smoke" / "report.json").read_text())
    page = render_html(nvs)
    assert "21.5 dB" in page and "0.701" in page and "37.2 dB" in page
    assert "LPIPS: LPIPS weights not available" in page
