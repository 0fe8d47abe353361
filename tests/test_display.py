"""How report values read: one format per metric kind, table titles, null reasons.

Fast tier: pure functions of :mod:`benchmark.display`, and the table numbers of its
titles checked against the paper's LaTeX source (skipped where the source is absent).
"""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from benchmark.display import (
    ARI_FAMILY,
    NULL,
    TABLE_TITLES,
    fmt_metric,
    metric_kind,
    metric_label,
    reason_text,
    table_description,
    table_ref,
    table_title,
)
from benchmark.paper_numbers import NA_REASON, NOT_REPORTED_REASON, PAPER_TABLES
from benchmark.schema import METRIC_UNITS

TEX = Path("/work/shared/paper/svorf_neurips2023.tex")


@pytest.mark.parametrize(
    "metric,value,text",
    [
        # ARI family: the paper's 0-100 scale (stored in percent), one decimal.
        ("fg_ari", 92.0, "92.0"),
        ("ari", 0.30841, "0.3"),
        ("nv_ari", -3.8512, "-3.9"),
        ("ari", 0, "0.0"),
        ("fg_ari", -0.04, "0.0"),  # no "-0.0"
        ("fg_ari_shuffled", 23.57, "23.6"),
        ("fg_ari_gain", -4.08, "-4.1"),
        ("chance_fg_ari", 80.65, "80.7"),
        ("ari_all", 100.0, "100.0"),
        # PSNR one decimal, dB; SSIM / LPIPS three decimals.
        ("psnr", 37.2, "37.2 dB"),
        ("psnr", 29.41, "29.4 dB"),
        ("ssim", 0.9701, "0.970"),
        ("lpips", 0.0211, "0.021"),
        # Times and memory with units; ratios with x.
        ("epoch_time_s", 204.0, "204 s"),
        ("step_time_s", 0.0123, "12.3 ms"),
        ("step_time_s", 4.2e-5, "42.0 \u00b5s"),
        ("epoch_time_s", 1050.0, "17.5 min"),
        ("epoch_time_s", 12000.0, "3.3 h"),
        ("render_s_per_view", 1.234, "1.23 s"),
        ("memory_gb", 4.6, "4.6 GB"),
        ("memory_gb", 0.391, "0.39 GB"),
        ("peak_memory_mb", 512.3, "512 MiB"),
        ("step_time_ratio", 2.504, "2.50x"),
        ("steps_per_s", 12.345, "12.3/s"),
        ("nonfinite_count", 3.0, "3"),
        ("max_abs_err_rgb", 2.04e-7, "2.0e-07"),
        ("max_abs_err_rgb", 0.0, "0"),
        ("depth_abs_rel", 0.19751, "0.198"),
        ("fg_ari", None, NULL),
    ],
)
def test_one_format_per_metric_kind(metric, value, text):
    assert fmt_metric(metric, value) == text


def test_every_metric_has_a_kind_and_a_label():
    for m in METRIC_UNITS:
        assert metric_kind(m) in {
            "ari",
            "psnr",
            "similarity",
            "time",
            "memory",
            "ratio",
            "rate",
            "count",
            "error",
            "fraction",
            "plain",
        }
        assert metric_label(m) and "_" not in metric_label(m), m
    # Every metric stored in percent is formatted as the ARI family, and the reverse.
    percent = {m for m, u in METRIC_UNITS.items() if u.startswith("percent")}
    assert percent == ARI_FAMILY - {"chance_fg_ari"}
    assert metric_label("fg_ari") == "FG-ARI" and metric_label("ari_all") == "ARI*"


def test_units_can_stay_in_the_header():
    assert fmt_metric("psnr", 37.21, unit=False) == "37.2"
    assert fmt_metric("memory_gb", 4.6, unit=False) == "4.6"


def test_every_table_has_a_readable_title():
    for table in PAPER_TABLES:
        title = table_title(table)
        assert title in TABLE_TITLES.values()
        assert not re.search(r"\b(tab|text):", title), title
        assert not re.search(r"\b(tab|text):", table_description(table)), table
    assert table_title("tab:seg") == "Segmentation (Table 1)"
    assert table_title("tab:ab_apparance") == "Held-out appearance (Table 6)"
    assert table_ref("tab:ablation") == "Table 5"
    # The benchmark's own tables keep readable ids as they are.
    assert table_title("tradeoff: init weights") == "tradeoff: init weights"
    # The description drops the table number the title already gives.
    assert table_description("tab:seg") == "Scene segmentation results."


@pytest.mark.skipif(not TEX.is_file(), reason=f"paper source {TEX} not on this machine")
def test_table_numbers_in_titles_follow_the_paper():
    """Number the paper's tables in source order (table / table* / wraptable environments
    and \\captionof{table}; the appendix continues the count) and compare with the titles."""
    tex = TEX.read_text()
    number, found = 0, {}
    sub = 0
    for m in re.finditer(
        r"\\begin\{(?:table\*?|wraptable)\}|\\captionof\{table\}|\\subfloat|\\label\{([^}]+)\}",
        tex,
    ):
        text = m.group(0)
        if text.startswith(("\\begin", "\\captionof")):
            number, sub = number + 1, 0
        elif text == "\\subfloat":
            sub += 1
        elif m.group(1) and m.group(1).startswith("tab:"):
            found[m.group(1)] = f"Table {number}" + ("abcdefgh"[sub - 1] if sub else "")
    for table in PAPER_TABLES:
        if table.startswith("tab:"):
            assert table_ref(table).split(",")[0] == found[table], (table, found[table])


def test_null_reasons_read_as_words():
    assert reason_text(NA_REASON) == "not in the paper"
    assert reason_text(NOT_REPORTED_REASON) == "not reported in the paper"
    assert reason_text("failed: RuntimeError: boom") == "row failed: RuntimeError: boom"
    assert reason_text("no_finite_value (NaN/inf in every scene)").startswith("no finite value (")
    assert reason_text("lpips_unavailable") == "LPIPS weights not available"
    assert reason_text("a sentence already") == "a sentence already"
