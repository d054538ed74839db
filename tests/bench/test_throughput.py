"""Tests of bench/throughput.py: the layouts, the workers' environment and a tiny end-to-end
run with real worker processes (no timings asserted)."""

from __future__ import annotations

import json
import os
from pathlib import Path

import pytest

from bench import throughput
from models.decoders.learned import THREADS_ENV
from models.metrics import PSNR_CAP
from tests.bench.exact_frames import exact_and_wrong


def test_layouts_fill_the_cores_three_ways_and_one_core_one_way() -> None:
    assert throughput.layouts(2) == [(1, 1, 2), (1, 2, 1), (2, 1, 1)]
    assert throughput.layouts(1) == [(1, 1, 1)]


def test_thread_limits_set_the_workers_threads_and_restore_the_parents(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.setenv(THREADS_ENV, "7")
    monkeypatch.delenv("OMP_NUM_THREADS", raising=False)
    assert throughput.THREAD_VARIABLES[0] == THREADS_ENV
    with throughput.thread_limits(1):
        assert all(os.environ[name] == "1" for name in throughput.THREAD_VARIABLES)
    assert os.environ[THREADS_ENV] == "7"
    assert "OMP_NUM_THREADS" not in os.environ


def test_two_worker_processes_decode_every_frame_of_their_share(tmp_path: Path) -> None:
    out = tmp_path / "throughput.json"
    assert throughput.main(
        ["--decoders", "itoh", "--frames", "2", "--repeats", "2", "--cores", "2",
         "--out", str(out)]
    ) == 0  # fmt: skip
    report = json.loads(out.read_text())
    [row] = report["results"]
    assert row["decoder"] == "itoh" and row["psnr_db"] > 0
    found = {layout["layout"]: layout for layout in row["layouts"]}
    assert set(found) == {"1 x 1 x 2", "1 x 2 x 1", "2 x 1 x 1"}
    # Every worker decodes its frames ``repeats`` times on each job thread.
    assert found["1 x 1 x 2"]["frames"] == 4
    assert found["1 x 2 x 1"]["frames"] == 8
    assert found["2 x 1 x 1"]["frames"] == 8
    assert all(layout["frames_per_s"] > 0 for layout in found.values())
    # One stream through a decode pool of 2: every frame ``repeats`` times, in order.
    assert row["stream_pool"]["processes"] == 2 and row["stream_pool"]["frames"] == 4
    table = out.with_suffix(".md").read_text()
    assert "| itoh |" in table and "2 x 1 x 1" in table
    assert "one stream in order, 2 processes" in table


def test_unknown_decoders_and_counts_below_one_are_refused(
    capsys: pytest.CaptureFixture[str],
) -> None:
    with pytest.raises(SystemExit):
        throughput.parse_args(["--decoders", "nope"])
    assert "unknown decoders nope" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        throughput.parse_args(["--repeats", "0"])
    assert "must be at least 1, got 0" in capsys.readouterr().err


def test_more_cores_than_the_machine_has_is_a_usage_error(
    capsys: pytest.CaptureFixture[str],
) -> None:
    """The layouts shared the cores and the report said that many cores were filled."""
    cores = os.cpu_count() or 1
    with pytest.raises(SystemExit) as exc:
        throughput.parse_args(["--cores", str(cores + 1)])
    assert exc.value.code == 2
    assert f"--cores {cores + 1} is more than this machine's {cores} cores" in (
        capsys.readouterr().err
    )
    assert throughput.parse_args(["--cores", str(cores)]).cores == cores


def test_a_worker_process_that_fails_ends_the_run_with_one_line() -> None:
    with pytest.raises(SystemExit) as stopped:
        throughput.measure_layout(
            "no-such-decoder", throughput.FrameSet("mantissa", 1), (2, 1, 1), 1
        )
    assert "a worker process failed (exit code 1)" in str(stopped.value.code)


def test_an_exact_frame_counts_at_the_psnr_cap() -> None:
    """Its inf made the decoder's mean PSNR inf."""
    frames = exact_and_wrong()
    assert throughput.mean_psnr("itoh", frames) == pytest.approx(
        (PSNR_CAP + throughput.mean_psnr("itoh", frames[1:])) / 2
    )
