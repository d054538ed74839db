"""Tests of bench/accuracy.py and bench/__init__.py: helpers and a tiny real run
(2 val-256 frames, no timings asserted)."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from bench import accuracy, json_safe, machine, versions
from models.errors import InvalidInputError
from models.formation import dequantize
from models.metrics import PSNR_CAP
from models.scenes import val256_frames
from tests.bench.virtual_clock import LATER_NS, PricedItoh, VirtualClock

ROOT = Path(__file__).resolve().parents[2]


def test_smoke_run_as_a_module_writes_json_and_markdown(tmp_path: Path) -> None:
    out = tmp_path / "accuracy.json"
    done = subprocess.run(
        [sys.executable, "-m", "bench.accuracy", "--decoders", "itoh", "graphcut",
         "--frames", "2", "--repeats", "2", "--time-frames", "1", "--noise-levels", "0",
         "--out", str(out)],
        cwd=ROOT, capture_output=True, text=True, timeout=280, check=False,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr
    report = json.loads(out.read_text())
    rows = report["results"]
    assert [(r["decoder"], r["encoding"]) for r in rows] == [
        ("itoh", "modulo"),
        ("graphcut", "modulo"),
        ("itoh", "mantissa"),
        ("graphcut", "mantissa"),
    ]
    for row in rows:
        assert row["frames"] == 2
        assert row["timed_runs"] == 3
        assert 0.0 <= row["winding_accuracy"] <= 1.0
        assert 0.0 < row["ssim"] <= 1.0
        assert row["ms_per_frame"] > 0.0
        assert row["psnr"] > 0.0 and row["pu21_psnr"] > 0.0
    assert report["protocol"]["frames"] == 2
    assert report["machine"]["cores"] >= 1
    assert len(report["load_average"]) == 3
    assert report["noise"]["decoders"] == ["itoh"]
    assert [r["read_noise"] for r in report["noise"]["results"]] == [0.0]
    assert out.with_suffix(".md").read_text().strip() == done.stdout.strip()
    assert "| graphcut | classical | mantissa |" in done.stdout


def test_unknown_decoder_is_a_usage_error(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exc:
        accuracy.parse_args(["--decoders", "no-such-decoder"])
    assert exc.value.code == 2
    assert "unknown decoders no-such-decoder" in capsys.readouterr().err


@pytest.mark.parametrize("flags", [["--frames", "0"], ["--repeats", "0"]])
def test_counts_must_be_positive(flags: list[str]) -> None:
    with pytest.raises(SystemExit):
        accuracy.parse_args(flags)


def test_mean_metrics_counts_an_exact_frame_at_the_cap_as_the_video_bench_does() -> None:
    """An exact frame (PSNR inf) was left out of the mean: a decoder exact on every frame
    but one at 20 dB read 20 dB, below one at 40 dB on every frame."""
    frames = [
        {"winding_accuracy": 1.0, "psnr": math.inf, "pu21_psnr": math.inf, "ssim": 1.0},
        {"winding_accuracy": 0.5, "psnr": 20.0, "pu21_psnr": 30.0, "ssim": 0.5},
    ]
    summary = accuracy.mean_metrics(frames)
    assert summary["psnr"] == (PSNR_CAP + 20.0) / 2
    assert summary["pu21_psnr"] == (PSNR_CAP + 30.0) / 2
    assert summary["winding_accuracy"] == 0.75
    assert summary["exact_frames"] == 1
    assert math.isnan(summary["ms_ssim"])


@pytest.mark.parametrize(("key", "value"), [("psnr", -math.inf), ("psnr", math.nan),
                                             ("ssim", math.nan)])
def test_mean_metrics_refuses_a_metric_that_is_not_a_number(key: str, value: float) -> None:
    """-inf (an overflowed estimate) was counted as an exact frame, NaN dropped."""
    frame = {"winding_accuracy": 1.0, "psnr": 30.0, "pu21_psnr": 30.0, "ssim": 0.9, key: value}
    with pytest.raises(InvalidInputError):
        accuracy.mean_metrics([frame])


def test_noise_candidates_pick_the_best_tier_and_name_missing_twins() -> None:
    """mantissanet-xl is not installed, so neither is its twin: the table names both and
    shows the best installed tier with a noise-aware twin (tiny) beside it."""
    rows = [
        {"decoder": "itoh", "kind": "classical", "encoding": "mantissa", "psnr": 10.0},
        {"decoder": "mantissanet-tiny", "kind": "learned", "encoding": "mantissa", "psnr": 30.0},
        {"decoder": "mantissanet-xl", "kind": "learned", "encoding": "mantissa", "psnr": 35.0},
        {"decoder": "mantissanet-xl+puma", "kind": "refined", "encoding": "mantissa", "psnr": 40},
        {"decoder": "mantissanet-xl", "kind": "learned", "encoding": "modulo", "psnr": 50.0},
        {"decoder": "mantissanet-huge", "kind": None, "encoding": "mantissa", "missing": "none"},
    ]
    names, missing = accuracy.noise_candidates(rows)
    assert names == ["mantissanet-tiny", "mantissanet-tiny-noise", "itoh"]
    assert missing == ["mantissanet-xl", "mantissanet-xl-noise"]
    assert accuracy.noise_candidates(rows[:1])[1] == [
        "mantissanet-<best tier>",
        "mantissanet-<best tier>-noise",
    ]


def report_of(results: list[dict], noise: dict) -> dict:
    """A report of one val-256 frame with these rows and this noise table."""
    return {
        "date": "2026-01-01T00:00:00+00:00",
        "machine": {"cpu": "cpu", "cores": 2},
        "load_average": (0.5, 1.0, 1.5),
        "threads": 2,
        "protocol": {"frames": 1, "size": 256, "overexposed": 0.2, "max_wraps": 16, "bits": 8},
        "results": results,
        "noise": {"encoding": "mantissa", **noise},
    }


def test_markdown_shows_missing_rows() -> None:
    report = report_of(
        [{"decoder": "x", "kind": "learned", "encoding": "modulo", "missing": "no model"}],
        {"levels": [0.0], "decoders": [], "missing": ["y"]},
    )
    text = accuracy.markdown(report)
    assert "| x | learned | modulo | n/a: no model |" in text
    assert "Not installed, so not in the noise table: y." in text


def test_no_noise_level_leaves_the_noise_table_out() -> None:
    """``--noise-levels`` with no value (its help: "none skips it") printed the table's
    header with one column too many and an empty row per decoder."""
    report = report_of([], {"levels": [], "decoders": ["itoh"], "missing": [], "results": []})
    text = accuracy.markdown(report)
    assert "against read noise" not in text and "| itoh |" not in text


def test_no_tier_measured_is_not_called_not_installed() -> None:
    """With ``--decoders itoh`` the note read "Not installed, so not in the noise table:
    mantissanet-<best tier>, ...", though every tier was installed, just not measured."""
    missing = list(accuracy.noise_candidates([])[1])
    noise = {"levels": [0.0], "decoders": ["itoh"], "missing": missing, "results": []}
    text = accuracy.markdown(report_of([], noise))
    assert "Not installed" not in text
    assert "No mantissanet tier was measured (none is installed, or --decoders named" in text


def test_json_safe_replaces_non_finite_floats() -> None:
    assert json_safe({"a": [math.inf, 1.0, (math.nan,)], "b": "s"}) == {
        "a": [None, 1.0, [None]],
        "b": "s",
    }


def test_machine_and_versions_are_recorded() -> None:
    assert machine()["cpu"]
    assert versions()["PyMaxflow"]


def test_winding_recall_counts_right_pixels_per_true_winding() -> None:
    truth = np.array([[0, 0, 1, 1], [2, 6, 7, 0]])
    estimate = np.array([[0, 1, 1, 0], [2, 6, 5, 0]])
    recall = accuracy.winding_recall([(estimate, truth)])
    assert recall["0"] == 2 / 3 and recall["1"] == 0.5 and recall["2"] == 1.0
    assert recall["3"] is None and recall["5+"] == 0.5


def test_ms_per_frame_is_the_median_over_frames_of_each_frame_s_median() -> None:
    """The times were pooled: the frames timed repeatedly (the first scene's) counted
    ``repeats`` times, so one slow frame timed 3 times among 3 frames made the median."""
    clock = VirtualClock()
    frames = val256_frames("mantissa")[:3]
    slow = dequantize(frames[0].codes, frames[0].params.bits).tobytes()
    decoder = PricedItoh(clock, lambda m: (10 if m.tobytes() == slow else 1) * LATER_NS)
    row = accuracy.measure(decoder, frames, repeats=3, time_frames=1, clock=clock)
    assert row["ms_per_frame"] == LATER_NS / 1e6
    assert row["timed_runs"] == 5
