"""Tests of bench/video.py: the summary's ratios and targets, and a tiny end-to-end run
(no timings asserted)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from bench import video
from models.video_clips import make_clip
from tests.bench.virtual_clock import LATER_NS, SlowFirstItoh, VirtualClock
from worker.temporal import StreamDecoder


def mode_row(mode: str, flicker: float, psnr: float, ms: float) -> dict:
    return {"clip": "sunrise", "encoding": "modulo", "decoder": "itoh", "mode": mode,
            "wrap_flicker": flicker, "psnr": psnr, "pu21_psnr": psnr + 1.0, "ms_per_frame": ms}


def test_summary_compares_the_two_modes_and_names_the_targets_met() -> None:
    rows = [mode_row("independent", 0.1, 20.0, 10.0), mode_row("temporal", 0.005, 21.5, 12.0)]
    (item,) = video.summarize(rows)
    assert item["flicker_reduction"] == pytest.approx(20.0)
    assert item["psnr_gain_db"] == pytest.approx(1.5)
    assert item["cost_ratio"] == pytest.approx(1.2)
    assert item["targets_met"] == {"flicker_10x": True, "psnr_gain": True, "cheaper": False}
    table = video.markdown_table([item], [[1.0, 1.0, 1.0], [2.0, 2.0, 2.0]])
    assert "| sunrise | modulo | itoh |" in table and "flicker_10x, psnr_gain |" in table


def test_a_clip_with_no_flicker_in_either_mode_meets_the_flicker_target() -> None:
    """It read '0.0 x less' and the 10x target as missed."""
    rows = [mode_row("independent", 0.0, 20.0, 10.0), mode_row("temporal", 0.0, 20.5, 8.0)]
    (item,) = video.summarize(rows)
    assert item["flicker_reduction"] is None and item["targets_met"]["flicker_10x"]
    assert "| - |" in video.markdown_table([item], [[1.0] * 3, [1.0] * 3])


def test_tiny_run_writes_json_and_markdown(tmp_path: Path) -> None:
    out = tmp_path / "video.json"
    video.main(["--clips", "static_noise", "--encodings", "modulo", "--decoders", "itoh",
                "--frames", "3", "--output", str(out)])  # fmt: skip
    report = json.loads(out.read_text())
    assert [row["mode"] for row in report["rows"]] == ["independent", "temporal"]
    assert report["rows"][1]["keyframes"] == 1
    assert report["config"]["motion"]["search"] > 0
    assert len(report["load_average"]) == len(report["load_average_at_start"]) == 3
    assert "Load average (1/5/15 min) at start [" in out.with_suffix(".md").read_text()
    assert "| static_noise | modulo | itoh |" in out.with_suffix(".md").read_text()


def test_a_mode_s_time_per_frame_leaves_out_the_decoder_s_first_call() -> None:
    """The first mode timed paid for the decoder's warm-up (a net's ONNX session), which
    made the temporal mode look cheaper than the independent one."""
    enc = make_clip("static_noise", frames=3, encodings=("modulo",)).encodings["modulo"]
    clock = VirtualClock()
    decoder = StreamDecoder("independent", SlowFirstItoh(clock))
    row = video.run_mode(enc, decoder, clock)
    assert row["ms_per_frame"] == pytest.approx(LATER_NS / 1e6)


def test_flicker_all_gone_reads_as_such_not_as_a_ratio_over_a_tiny_floor() -> None:
    """Independent flicker over a floor of 1e-12 read '50000000000.0 x less'."""
    rows = [mode_row("independent", 0.05, 20.0, 10.0), mode_row("temporal", 0.0, 21.0, 8.0)]
    (item,) = video.summarize(rows)
    assert item["flicker_reduction"] == float("inf") and item["targets_met"]["flicker_10x"]
    assert "| 0.05000 -> 0.00000 | all |" in video.markdown_table([item], [[1.0] * 3] * 2)


def test_all_with_other_decoders_is_refused_as_such(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """``--decoders all,itoh`` was refused as "unknown decoders all", though the help
    offers 'all' (it stands alone)."""
    with pytest.raises(SystemExit) as exc:
        video.main(["--decoders", "all,itoh", "--output", str(tmp_path / "v.json")])
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert (
        "--decoders: 'all' (every installed decoder) goes alone, got all,itoh; give "
        "--decoders all, or name the decoders only" in err
    )
    assert "unknown decoders" not in err
