"""The command lines' errors and help: every error is one line on stderr that says what
was wrong and how to fix it ("did you mean ...?" for a misspelt name), with exit status 2
for bad usage; ``--help`` shows defaults and mentions nothing outside the repository (nor
does any message, docstring, comment or user doc); and ``benchmark run`` prints each
verdict, the data folder and each report path once.

No training, rendering or dataset generation: every bad input is refused before any work
(seconds in all; two subprocess runs check the real entry points).
"""

from __future__ import annotations

import argparse
import re
import subprocess
import sys
import time
import tokenize
from pathlib import Path

import pytest

from benchmark.cli import main as benchmark_main
from benchmark.cli import summary_lines
from benchmark.tools.recipe import main as recipe_main
from generators.cli import main as generate_main
from scenefmt import cli_util
from scenefmt.cli_util import OneLineParser, choose, did_you_mean, doc_summary, error_line
from svorf.cli import main as svorf_main

ROOT = Path(__file__).resolve().parents[1]

#: References to texts that are not in the repository.
DANGLING = re.compile(r"issue \d|DESIGN", re.IGNORECASE)


def _one_line_error(capsys: pytest.CaptureFixture[str], prog: str) -> str:
    """The single stderr line of a failed command (asserted: one line, ``PROG: error:``)."""
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.endswith("\n"), err
    assert err.startswith(f"{prog}: error: "), err
    return err.strip()


def _status(main, argv: list[str]) -> int:
    """Exit status of ``main(argv)``, whether it returns it or exits (argparse)."""
    try:
        return main(argv)
    except SystemExit as e:
        return int(e.code or 0)


# ------------------------------------------------------------------ the shared helper


def test_choose_and_did_you_mean():
    assert choose("smoke", ("smoke", "cpu", "paper"), "scale") == "smoke"
    with pytest.raises(ValueError) as e:
        choose("smok", ("smoke", "cpu", "paper"), "scale")
    assert str(e.value) == (
        "unknown scale 'smok'; did you mean 'smoke'? (choose from smoke, cpu, paper)"
    )
    assert did_you_mean("zzz", ["smoke", "cpu"]) == ""
    assert error_line(FileNotFoundError(2, "No such file or directory", "x/report.json")) == (
        "x/report.json: no such file or directory"
    )
    assert error_line(ValueError("first\nsecond")) == "first"
    assert doc_summary('"""A sentence\nover two lines.\n\nMore."""'.strip('"')) == (
        "A sentence over two lines."
    )


def test_one_line_parser_defaults_and_choice_errors(capsys):
    p = OneLineParser(prog="tool")
    sub = p.add_subparsers(dest="cmd", required=True)
    r = sub.add_parser("run", help="run it")
    r.add_argument("--scale", default="smoke", choices=("smoke", "cpu"), help="size")
    r.add_argument("--quiet", action="store_true", help="say less")
    r.add_argument("--n", type=int, default=None, help="count")
    text = r.format_help()
    assert "size (default: smoke)" in text
    assert "say less\n" in text and "count\n" in text  # no "(default: False/None)"
    with pytest.raises(SystemExit) as e:
        p.parse_args(["run", "--scale", "cpuu"])
    assert e.value.code == 2
    err = _one_line_error(capsys, "tool")
    assert "did you mean 'cpu'?" in err and "(see `tool run --help`)" in err
    assert "tool: error: tool run" not in err
    with pytest.raises(SystemExit):
        p.parse_args(["rnu"])
    assert "unknown command 'rnu'; did you mean 'run'?" in _one_line_error(capsys, "tool")
    assert isinstance(r, argparse.ArgumentParser)


# ------------------------------------------------------------------ generate


@pytest.mark.parametrize(
    "argv, needle",
    [
        (["--preset", "clever567"], "unknown preset 'clever567'; did you mean 'clevr567'?"),
        (["preview", "--preset", "clever567"], "did you mean 'clevr567'?"),
        (["verfy", "data/x"], "unknown command 'verfy'; did you mean 'verify'?"),
        (["--preset", "clevr567", "--backend", "rai"], "did you mean 'ray'?"),
    ],
)
def test_generate_errors_are_one_line_with_a_hint(tmp_path, capsys, argv, needle):
    out = tmp_path / "out"
    assert _status(generate_main, [*argv, "--out", str(out)]) == 2
    assert needle in _one_line_error(capsys, "generate")
    assert not out.exists()


def test_generate_verify_of_a_missing_folder(tmp_path, capsys):
    assert generate_main(["verify", str(tmp_path / "nope")]) == 2
    err = _one_line_error(capsys, "generate")
    assert "nope: no such folder" in err and "pass a split folder" in err


def test_generate_help_shows_defaults_and_preview_help_texts(capsys):
    assert _status(generate_main, ["--help"]) == 0
    text = capsys.readouterr().out
    assert re.search(r"square image size.*\(default: 128\)", text, re.DOTALL)
    assert _status(generate_main, ["preview", "--help"]) == 0
    text = capsys.readouterr().out
    for needle in ("one of: clevr567", "(default: 4)", "(default: 128)", "preview.png"):
        assert needle in text, needle


# ------------------------------------------------------------------ svorf


@pytest.mark.parametrize(
    "argv, needle",
    [
        (["--preset", "clever567", "--scale", "smoke"], "did you mean 'clevr567'?"),
        (["--preset", "clevr567", "--scale", "smok"], "did you mean 'smoke'?"),
    ],
)
def test_svorf_train_bad_names_one_clean_line(tmp_path, capsys, argv, needle):
    base = ["train", "--data", str(tmp_path), "--out", str(tmp_path / "run")]
    assert svorf_main([*base, *argv]) == 2
    err = _one_line_error(capsys, "svorf")
    assert needle in err and "svorf train: " not in err and "`svorf train --help`" in err


def test_svorf_misspelt_command(capsys):
    assert svorf_main(["trian"]) == 2
    assert "did you mean 'train'?" in _one_line_error(capsys, "svorf")


def test_svorf_train_rerun_names_the_flags_not_python(tmp_path, capsys):
    run = tmp_path / "run"
    run.mkdir()
    (run / "checkpoint.pt").write_bytes(b"x")
    argv = ["train", "--data", str(tmp_path), "--preset", "synthetic", "--scale", "smoke"]
    assert svorf_main([*argv, "--out", str(run)]) == 2
    err = _one_line_error(capsys, "svorf")
    assert "--resume" in err and "--out DIR" in err and "resume=True" not in err


def test_recipe_help_is_whole_and_errors_one_line(tmp_path, capsys):
    assert recipe_main(["--help"]) == 0
    text = capsys.readouterr().out
    assert "and the recipe's levers as config fields." in " ".join(text.split())  # whole
    assert not DANGLING.search(text)
    assert (
        recipe_main(
            [
                "train-eval",
                "--data",
                "a",
                "--test",
                "b",
                "--out",
                "c",
                "--minutes",
                "1",
                "--preset",
                "clevr56",
            ]
        )
        == 2
    )
    assert "did you mean 'clevr567'?" in _one_line_error(capsys, "python -m benchmark.tools.recipe")
    run = tmp_path / "run"
    run.mkdir()
    (run / "checkpoint.pt").write_bytes(b"x")
    argv = ["train-eval", "--data", "a", "--test", "b", "--out", str(run), "--minutes", "1"]
    assert recipe_main(argv) == 2
    assert "--resume" in _one_line_error(capsys, "python -m benchmark.tools.recipe")
    argv = ["train-eval", "--data", "a", "--test", "b", "--out", str(tmp_path / "new"),
            "--minutes", "1"]  # fmt: skip
    for bad, says in (("target_sise=128", "target_sise"), ("target_size=4", "target_size")):
        assert recipe_main([*argv, "--train-set", bad]) == 2
        err = _one_line_error(capsys, "python -m benchmark.tools.recipe")
        assert says in err and "--train-set" in err


# ------------------------------------------------------------------ benchmark


def _bench(tmp: Path, *argv: str) -> int:
    return benchmark_main(
        [
            *argv,
            "--out",
            str(tmp / "reports"),
            "--data",
            str(tmp / "data"),
            "--data-source",
            "synthetic",
            "--no-progress",
        ]
    )


@pytest.mark.parametrize(
    "argv, needle",
    [
        (("run", "segmentation", "--scale", "smok"), "did you mean 'smoke'?"),
        (("run", "segmentaton"), "unknown protocol 'segmentaton'; did you mean 'segmentation'?"),
        (("run", "segmentation", "--datasets", "clevr56"), "did you mean 'clevr567'?"),
        (("run", "nvs", "--data-source", "synth"), "did you mean 'synthetic'?"),
    ],
)
def test_benchmark_run_bad_names_one_line(tmp_path, capsys, argv, needle):
    assert _bench(tmp_path, *argv) == 2
    assert needle in _one_line_error(capsys, "benchmark")
    assert not (tmp_path / "data").exists()  # refused before any work


@pytest.mark.parametrize("cmd", ["html", "screenshot", "leaderboard"])
def test_benchmark_folder_commands_name_the_folder(tmp_path, capsys, cmd):
    missing = tmp_path / "nosuchdir"
    assert benchmark_main([cmd, str(missing)]) == 2
    err = _one_line_error(capsys, "benchmark")
    assert f"{missing}: no such folder; pass " in err and "Errno" not in err
    if cmd == "html":  # a folder without report.json
        assert benchmark_main([cmd, str(tmp_path)]) == 2
        assert "no report.json" in _one_line_error(capsys, "benchmark")


def test_benchmark_run_help_shows_the_default_scale(capsys):
    assert benchmark_main(["run", "--help"]) == 0
    assert "(default: smoke)" in capsys.readouterr().out


def test_benchmark_summary_prints_each_thing_once(tmp_path):
    """The ablation's full model is a row of two tables: one verdict line, not two."""
    msg = "does NOT decompose at scale 'smoke': ..."
    verdict = {
        "dataset": "clevr567",
        "model": "sVORF (ours)",
        "decomposes": False,
        "fg_ari": 19.5,
        "chance_fg_ari": 80.7,
        "fg_ari_shuffled": 23.6,
        "message": msg,
    }
    report = {
        "protocol": "ablation",
        "scale": "smoke",
        "status": "complete",
        "wall_time_s": {"total": 1.0},
        "scale_settings": {"benchmark": {"decompose_threshold": 50.0, "decompose_margin": 20.0}},
        "rows": [],
        "verdicts": [
            {**verdict, "table": "tab:ablation"},
            {**verdict, "table": "tab:supp_ablation"},
            {**verdict, "model": "sVORF (w/o NVS)", "table": "tab:ablation"},
        ],
        "models": [
            {
                "variant": v,
                "train_dataset": "clevr567/train",
                "train_wall_s": 60.0,
                "train_budget": {"steps_done": 10, "stopped_by": "steps"},
                "weights_scored": w,
                "run_key": "0123456789abcdef",
            }
            for v, w in (("full", "ema"), ("w/o NVS", "raw"))
        ],
        "datasets": [
            {
                "name": n,
                "path": str(tmp_path / "data" / "smoke" / n),
                "generated_now": i == 0,
                "deviations": [] if i == 0 else ["0 data seed (nominal 1)"],
            }
            for i, n in enumerate(("clevr567/test", "clevr567/train"))
        ],
    }
    path = tmp_path / "reports" / "ablation-smoke" / "report.json"
    text = "\n".join(summary_lines(report, path))
    assert text.count("does NOT decompose") == 1
    (ema,) = [line for line in text.splitlines() if "scored with its moving average" in line]
    assert ema.startswith("  full on clevr567/train: 10 steps, 1.0 min training, stopped by steps")
    assert text.count("clevr567 / sVORF (ours)") == 1 and "sVORF (w/o NVS)" in text
    assert text.count(str(path)) == 1 and text.count("index.html") == 1
    assert f"data:   {tmp_path / 'data' / 'smoke' / 'clevr567'} (2 splits: generated now " in text
    # a split found on disk says how it deviates (here: an earlier run's data seed)
    assert "found on disk clevr567/train [0 data seed (nominal 1)])" in text
    assert text.splitlines()[-2:] == [
        f"report: {path}",
        f"page:   {path.parent / 'index.html'}",
    ]


# ------------------------------------------------------------------ help texts, subprocess


def _helps() -> dict[str, str]:
    from benchmark.cli import _parser as benchmark_parser
    from generators.cli import _gen_parser
    from svorf.cli import _parser as svorf_parser

    out = {"generate": _gen_parser().format_help()}
    for name, p in (("svorf", svorf_parser()), ("benchmark", benchmark_parser())):
        out[name] = p.format_help()
        sub = next(a for a in p._actions if isinstance(a, argparse._SubParsersAction))
        out.update({f"{name} {k}": v.format_help() for k, v in sub.choices.items()})
    return out


def test_help_texts_mention_nothing_outside_the_repository():
    for name, text in _helps().items():
        assert not DANGLING.search(text), (name, DANGLING.search(text))


#: What a message, report note, docstring or comment must not lean on: a tracker's issue,
#: a design file outside the repository, or the folder beside the checkout.
OUTSIDE = re.compile(
    r"\bthe issue\b|\bissue's\b|\bissues? #?\d|DESIGN\.md|\.\./shared", re.IGNORECASE
)


def test_sources_mention_nothing_outside_the_repository():
    """Every string literal (messages, report notes, help, docstrings) and every comment of
    the packages and tests (a report's notes are written from these strings), and the user
    docs: the README and ``docs/*.md`` (the lab diaries under ``docs/notes/`` are history)."""
    found = [
        str(path.relative_to(ROOT))
        for path in (ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md")))
        if OUTSIDE.search(path.read_text())
    ]
    for pkg in ("svorf", "benchmark", "generators", "scenefmt", "assets_procedural", "tests"):
        for path in sorted((ROOT / pkg).rglob("*.py")):
            with path.open("rb") as f:
                for tok in tokenize.tokenize(f.readline):
                    if tok.type in (tokenize.STRING, tokenize.COMMENT) and OUTSIDE.search(
                        tok.string
                    ):
                        found.append(f"{path.relative_to(ROOT)}:{tok.start[0]}")
    assert not found, found


@pytest.mark.parametrize(
    "module", ["benchmark.tools.speedbench", "benchmark.scaling", "benchmark.tools.recipe"]
)
def test_tool_descriptions_are_whole_sentences(module):
    r = subprocess.run(
        [sys.executable, "-m", module, "--help"],
        check=False,
        capture_output=True,
        text=True,
        cwd=ROOT,
        timeout=120,
    )
    assert r.returncode == 0, r.stderr
    desc = r.stdout.split("\n\n")[1]  # usage, description, options
    assert desc.rstrip().endswith("."), desc
    assert not DANGLING.search(r.stdout)


def test_benchmark_bad_scale_from_the_real_entry_point(tmp_path):
    r = subprocess.run(
        [
            sys.executable,
            "-m",
            "benchmark.cli",
            "run",
            "segmentation",
            "--scale",
            "smok",
            "--out",
            str(tmp_path),
            "--data",
            str(tmp_path),
        ],
        check=False,
        capture_output=True,
        text=True,
        cwd=ROOT,
        timeout=120,
    )
    assert r.returncode == 2 and r.stdout == ""
    assert r.stderr.count("\n") == 1 and "did you mean 'smoke'?" in r.stderr


def test_progress_bars_redraw_rarely_into_a_log():
    """On a terminal tqdm keeps its pace; into a file or pipe it redraws at most every
    30 s, so a long run's log is not tens of thousands of bar records."""
    import doctest
    import io

    from tqdm import tqdm

    class Terminal(io.StringIO):
        def isatty(self) -> bool:
            return True

    class Closed(io.StringIO):
        def isatty(self) -> bool:
            raise ValueError("I/O operation on closed file")

    assert cli_util.progress_kwargs(Terminal()) == {}
    assert cli_util.progress_kwargs(Closed()) == cli_util.progress_kwargs(io.StringIO())
    assert doctest.testmod(cli_util).failed == 0
    log, term = io.StringIO(), Terminal()
    for out in (log, term):
        with tqdm(total=2000, file=out, **cli_util.progress_kwargs(out)) as bar:
            for _ in range(2000):
                bar.update(1)
                time.sleep(0.0004)  # about 0.8 s in all: several redraws on a terminal
    assert log.getvalue().count("\r") <= 3 < term.getvalue().count("\r")
    assert "2000/2000" in log.getvalue()
