"""Every benchmark refuses a name it does not know before it measures anything: a usage
error (exit code 2) naming the unknown value and what it accepts, never a traceback
after minutes of work, and never a silently smaller table."""

from __future__ import annotations

import subprocess
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest

from bench import (
    accuracy,
    colour,
    headroom,
    losses,
    profile,
    service,
    stream,
    throughput,
    tradeoff,
    video,
)
from models.decoders.learned import load_cards

ROOT = Path(__file__).resolve().parents[2]

MAINS: dict[str, Callable[[list[str] | None], Any]] = {
    "accuracy": accuracy.main,
    "colour": colour.main,
    "headroom": headroom.main,
    "profile": profile.main,
    "service": service.main,
    "stream": stream.main,
    "throughput": throughput.main,
    "tradeoff": tradeoff.main,
    "video": video.main,
}
#: Installed nets with a mantissa model and none for modulo (e.g. mantissanet-base-noise).
MANTISSA_ONLY = sorted(
    {card["decoder"] for card in load_cards()}
    - {card["decoder"] for card in load_cards() if card["encoding"] == "modulo"}
)


@pytest.mark.parametrize(
    ("bench", "argv", "message"),
    [
        ("colour", ["--decoders", "itoh", "nope"], "unknown decoders nope; choose from: itoh"),
        ("headroom", ["--decoders", "nope"], "unknown decoders nope"),
        ("profile", ["--models", "itoh"], "unknown models itoh; choose from: mantissanet-"),
        ("stream", ["--decoder", "nope"], "unknown decoders nope"),
        ("service", ["--decoder", "nope"], "unknown decoders nope; choose from: itoh"),
        ("stream", ["--stream-processes", "0"], "must be at least 1, got 0"),
        ("stream", ["--scenes", "mars"], "invalid choice: 'mars'"),
        ("tradeoff", ["--decoders", "auto-fast-tile48"], "unknown decoders auto-fast-tile48"),
        ("video", ["--decoders", "itoh,nope"], "unknown decoders nope"),
        ("video", ["--clips", "pan_zoom,orbit"], "unknown clips orbit; choose from: pan_zoom"),
        ("video", ["--encodings", "log"], "unknown encodings log; choose from: mantissa"),
        # An empty name (a comma too many) was refused as "unknown decoders ; choose ...".
        ("video", ["--decoders", "itoh,"], "--decoders: an empty name in 'itoh,': separate"),
        ("video", ["--clips", "pan_zoom,,sunrise"], "--clips: an empty name in 'pan_zoom,,"),
        # An empty name given apart was refused as "unknown decoders ; choose from ...".
        ("accuracy", ["--decoders", "itoh", ""], "an empty name among the decoders given"),
        ("service", ["--decoder", ""], "an empty name among the decoders given ('')"),
        ("profile", ["--models", " "], "an empty name among the models given (' ')"),
        # A name or value given twice was measured twice and reported twice (bench.video's
        # summary kept the second measurement alone).
        ("accuracy", ["--decoders", "itoh", "herraez", "itoh"],
         "argument --decoders: itoh given more than once; give each once"),
        ("accuracy", ["--noise-levels", "0", "0.0"], "argument --noise-levels: 0.0 given more"),
        ("colour", ["--sets", "val", "val"], "argument --sets: val given more than once"),
        ("headroom", ["--encodings", "modulo", "modulo"], "argument --encodings: modulo given"),
        ("profile", ["--models", "mantissanet-tiny", "mantissanet-tiny"],
         "argument --models: mantissanet-tiny given more than once"),
        ("throughput", ["--decoders", "itoh", "itoh"], "argument --decoders: itoh given more"),
        ("tradeoff", ["--decoders", "itoh", "itoh"], "argument --decoders: itoh given more"),
        ("video", ["--clips", "pan_zoom,sunrise,pan_zoom"],
         "argument --clips: pan_zoom given more than once; give each once"),
        # Counts and levels, refused before anything is measured (they gave NaN timings,
        # an IndexError after the matmul calibration, or a traceback after the main table).
        ("tradeoff", ["--repeats", "0"], "--repeats: must be at least 1, got 0"),
        ("tradeoff", ["--frames", "0"], "--frames: must be at least 1, got 0"),
        ("tradeoff", ["--dark", "0"], "--dark: must be at least 1, got 0"),
        ("tradeoff", ["--glows", "-1"], "--glows: must be at least 0, got -1"),
        ("accuracy", ["--noise-levels", "-0.1"], "a read noise is in [0, 1] wraps, got -0.1"),
        ("accuracy", ["--noise-levels", "nan"], "a read noise is in [0, 1] wraps, got nan"),
        ("colour", ["--read-noise", "2"], "a read noise is in [0, 1] wraps, got 2"),
        ("video", ["--frames", "1"], "--frames: must be at least 2, got 1"),
        ("video", ["--keyframe-interval", "-5"], "--keyframe-interval: must be at least 0, got -5"),
        ("profile", ["--runs", "x"], "'x' is not a whole number"),
        # More val-256 frames than the set has ran the whole set under the count asked.
        ("accuracy", ["--frames", "25"], "--frames: val-256 has 24 frames, got 25"),
        ("headroom", ["--frames", "30"], "--frames: val-256 has 24 frames, got 30"),
        ("throughput", ["--frames", "25"], "--frames: val-256 has 24 frames, got 25"),
        ("tradeoff", ["--frames", "100"], "--frames: val-256 has 24 frames, got 100"),
    ],
)
def test_unknown_names_are_usage_errors(
    bench: str, argv: list[str], message: str, capsys: pytest.CaptureFixture[str]
) -> None:
    with pytest.raises(SystemExit) as exc:
        MAINS[bench](argv)
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert message in err
    assert "Traceback" not in err


@pytest.mark.skipif(not MANTISSA_ONLY, reason="no installed net lacks a modulo model")
@pytest.mark.parametrize(
    ("bench", "argv"),
    [
        ("colour", ["--decoders", "itoh", "{net}", "--encodings", "modulo"]),
        ("headroom", ["--decoders", "{net}+puma2", "--encodings", "mantissa", "modulo"]),
        ("throughput", ["--decoders", "{net}", "--encoding", "modulo"]),
        ("stream", ["--decoder", "{net}"]),
        ("video", ["--decoders", "itoh,{net}", "--encodings", "modulo"]),
    ],
)
def test_a_decoder_without_a_model_for_an_encoding_is_a_usage_error(
    bench: str, argv: list[str], capsys: pytest.CaptureFixture[str]
) -> None:
    """It passed as a known decoder, then crashed in the middle of the run (the stream
    benchmark's camera frames are modulo)."""
    net = MANTISSA_ONLY[0]
    with pytest.raises(SystemExit) as exc:
        MAINS[bench]([arg.format(net=net) for arg in argv])
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert f"{net}" in err and "decodes mantissa, not modulo: choose other decoders" in err
    assert "Traceback" not in err


def test_tradeoff_accepts_its_own_tile_variants_and_parametrized_decoders() -> None:
    names = ["auto-fast-tile32", "mantissanet-tiny+puma2", "auto-40ms"]
    chosen = tradeoff.candidates(names)
    assert [name for name, _ in chosen] == names
    assert chosen[0][1].tile == 32


#: Each benchmark's smallest run and the option naming where its report goes.
SMALLEST: dict[str, tuple[list[str], str]] = {
    "accuracy": (["--decoders", "itoh", "--frames", "1", "--time-frames", "0",
                  "--repeats", "1", "--noise-levels"], "--out"),
    "colour": (["--decoders", "itoh", "--encodings", "mantissa", "--sets", "val",
                "--frames", "1"], "--out"),
    "headroom": (["--decoders", "itoh", "--encodings", "mantissa", "--frames", "1"], "--out"),
    "losses": (["--frames", "1"], "--out"),
    "profile": (["--models", "mantissanet-tiny", "--runs", "1", "--repeats", "1"], "--out"),
    "service": (["--jobs-per-client", "1"], "--out"),
    "stream": (["--frames", "1", "--workers", "1"], "--out"),
    "throughput": (["--decoders", "itoh", "--frames", "1", "--repeats", "1",
                    "--cores", "1"], "--out"),
    "tradeoff": (["--frames", "1", "--dark", "1", "--glows", "0", "--repeats", "1",
                  "--decoders", "itoh", "--quick"], "--out"),
    "video": (["--clips", "static_noise", "--encodings", "modulo", "--decoders", "itoh",
               "--frames", "2"], "--output"),
}  # fmt: skip


def refused(bench: str, argv: list[str], capsys: pytest.CaptureFixture[str]) -> str:
    """The one line of stderr ``bench`` ends ``argv`` with (exit code 2)."""
    with pytest.raises(SystemExit) as exc:
        {**MAINS, "losses": losses.main}[bench](argv)
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err
    return err


@pytest.mark.parametrize("bench", sorted(SMALLEST))
def test_a_folder_as_the_report_path_is_a_usage_error(
    bench: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """It measured everything, then ended in an IsADirectoryError traceback."""
    argv, flag = SMALLEST[bench]
    err = refused(bench, [*argv, flag, str(tmp_path)], capsys)
    assert f"{flag}: {tmp_path} is a folder; name a file in it" in err


@pytest.mark.parametrize("bench", sorted(SMALLEST))
def test_a_report_named_as_its_markdown_copy_is_a_usage_error(
    bench: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """The JSON report went to report.md, then its Markdown copy (.md beside it) replaced
    it: the measurements' JSON was lost after the whole run."""
    argv, flag = SMALLEST[bench]
    err = refused(bench, [*argv, flag, str(tmp_path / "report.md")], capsys)
    assert f"{flag}: {tmp_path / 'report.md'} names the report's Markdown copy" in err
    assert f"name the report {tmp_path / 'report.json'}" in err


@pytest.mark.parametrize("plot", ["t.json", "t.md"])
def test_a_plot_over_the_tradeoff_report_is_a_usage_error(
    plot: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """The plot, written after the report, replaced its JSON or its Markdown copy."""
    argv = [*SMALLEST["tradeoff"][0], "--out", str(tmp_path / "t.json")]
    err = refused("tradeoff", [*argv, "--plot", str(tmp_path / plot)], capsys)
    assert f"--plot: {tmp_path / plot} is a file of the report" in err
    assert f"e.g. {tmp_path / 't.png'}" in err


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["--out", "{tmp}/typo/accuracy.json"], "--out: folder {tmp}/typo does not exist"),
        (["--out", "/proc/accuracy.json"], "--out: cannot write in /proc ("),
        (["--out", "{tmp}/t.json", "--plot", "{tmp}"], "--plot: {tmp} is a folder"),
    ],
)
def test_a_report_path_that_cannot_be_written_is_a_usage_error(
    argv: list[str], message: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A missing folder was made (a typo made a stray folder) and an unwritable one ended
    the run in a traceback, both after the whole measurement."""
    if "/proc" in argv[-1] and not Path("/proc").is_dir():
        pytest.skip("no /proc here")
    bench = "tradeoff" if "--plot" in argv else "accuracy"
    small = SMALLEST[bench][0]
    err = refused(bench, [*small, *(arg.format(tmp=tmp_path) for arg in argv)], capsys)
    assert message.format(tmp=tmp_path) in err


@pytest.mark.parametrize(
    ("bench", "module", "extra", "argv"),
    [
        ("losses", "torch", "train", ["--help"]),
        ("service", "httpx", "bench", ["--help"]),
        ("tradeoff", "matplotlib", "bench",
         [*SMALLEST["tradeoff"][0], "--out", "{tmp}/t.json", "--plot", "{tmp}/t.png"]),
    ],
)  # fmt: skip
def test_a_missing_optional_dependency_is_named_with_the_extra_that_installs_it(
    bench: str, module: str, extra: str, argv: list[str], tmp_path: Path
) -> None:
    """Without the extra, bench.losses and bench.service ended in a ModuleNotFoundError
    traceback on start (``--help`` too), and bench.tradeoff after measuring, at its plot."""
    args = [arg.format(tmp=tmp_path) for arg in argv]
    code = (
        f"import runpy, sys; sys.modules[{module!r}] = None; sys.argv = ['x', *{args!r}]; "
        f"runpy.run_module('bench.{bench}', run_name='__main__')"
    )
    done = subprocess.run(
        [sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=280
    )
    assert done.returncode == 2, done.stderr
    assert done.stderr.splitlines() == [
        f"bench.{bench}{' (its --plot)' if bench == 'tradeoff' else ''}: error: it needs "
        f"{module}, which is not installed; install the '{extra}' extra: "
        f"pip install -c constraints.txt -e '.[{extra}]'"
    ]
    assert not (tmp_path / "t.json").exists()


@pytest.mark.parametrize("bench", sorted(SMALLEST))
def test_the_usage_line_names_the_command_that_runs_the_benchmark(
    bench: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """It named the script's file (``usage: accuracy.py``), and ``python accuracy.py``
    cannot import ``bench``."""
    argv, flag = SMALLEST[bench]
    err = refused(bench, [*argv, flag, str(tmp_path)], capsys)
    assert err.startswith(f"usage: python -m bench.{bench} ")
    assert f"\npython -m bench.{bench}: error: " in err
