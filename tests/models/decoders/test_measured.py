"""Tests of models/decoders/measured.py: each decoder's figures and their source."""

from __future__ import annotations

import json
import logging
from pathlib import Path

import pytest

from models.decoders.measured import benchmark_figures, measured_figures
from models.decoders.registry import DecoderSpec, available_decoders

ROW = {"winding_accuracy": 0.61234, "psnr": 18.123456, "pu21_psnr": 18.5, "ssim": 0.66,
       "ms_ssim": 0.7, "ms_per_frame": 1.4567}


def spec(name: str) -> DecoderSpec:
    return next(found for found in available_decoders() if found.name == name)


def write_report(path: Path) -> Path:
    report = {
        "date": "2026-11-27T05:36:18+00:00",
        "machine": {"cpu": "AMD EPYC"},
        "threads": 2,
        "versions": {"git_commit": "cb99f959cdb81dfcc1a30f8caa49f130a1ca9d04"},
        "results": [
            {"decoder": "itoh", "kind": "classical", "encoding": "mantissa", **ROW},
            {"decoder": "mantissanet-tiny-noise", "encoding": "modulo", "missing": "no model"},
        ],
        "noise": {"results": [
            {"read_noise": 0.0, "decoder": "itoh", "encoding": "mantissa", **ROW, "psnr": 1.0},
            {"read_noise": 0.01, "decoder": "itoh", "encoding": "mantissa", **ROW},
        ]},
    }
    path.write_text(json.dumps(report))
    return path


def test_a_decoder_without_a_card_takes_its_benchmark_rows(tmp_path: Path) -> None:
    bench = benchmark_figures(write_report(tmp_path / "accuracy.json"))
    assert bench is not None
    figures, source = measured_figures(spec("itoh"), bench)
    rounded = {**{k: round(v, 4) for k, v in ROW.items()}, "ms_per_frame": 1.46}
    assert figures == {"mantissa": {"val256": {"read_noise_0": rounded,
                                               "read_noise_0.01": rounded}}}
    assert "val-256 benchmark (python -m bench.accuracy) of 2026-11-27 on AMD EPYC" in source
    assert "2 threads, commit cb99f959cdb8" in source
    assert "mantissanet-tiny-noise" not in bench.by_decoder


def test_a_learned_decoder_keeps_its_cards_figures(tmp_path: Path) -> None:
    bench = benchmark_figures(write_report(tmp_path / "accuracy.json"))
    figures, source = measured_figures(spec("mantissanet-small"), bench)
    assert figures == spec("mantissanet-small").figures and figures["mantissa"]["val256"]
    assert source.startswith("model cards models/onnx/mantissanet-small-mantissa.json")


def test_no_figures_say_why_and_where_to_find_them(tmp_path: Path) -> None:
    assert benchmark_figures(tmp_path / "absent.json") is None
    figures, source = measured_figures(spec("graphcut"), None)
    assert figures == {}
    assert source.startswith("none measured in this installation")
    assert "bench/results/accuracy.json" in source and "python -m bench.accuracy" in source
    bench = benchmark_figures(write_report(tmp_path / "accuracy.json"))
    figures, source = measured_figures(spec("graphcut"), bench)
    assert figures == {} and "has no row for graphcut" in source


@pytest.mark.parametrize("text", [
    '{"date": "2026-11-27", "results": [',  # written partly
    '{"results": []}',  # no date
    '{"date": "2026-11-27", "results": [{"decoder": "itoh", "encoding": "mantissa", "psnr": 1}]}',
    '["not", "a", "report"]',
])
def test_an_unreadable_report_is_no_figures_logged_once(
    tmp_path: Path, text: str, caplog: pytest.LogCaptureFixture
) -> None:
    """A partly written report, or one missing a field, was a 500 on every GET /v1/decoders."""
    path = tmp_path / "accuracy.json"
    path.write_text(text)
    with caplog.at_level(logging.WARNING, logger="models.decoders.measured"):
        assert benchmark_figures(path) is None
        assert benchmark_figures(path) is None
    assert len(caplog.records) == 1 and "python -m bench.accuracy" in caplog.text
    figures, source = measured_figures(spec("itoh"), None)
    assert figures == {} and source.startswith("none measured in this installation")


def test_a_report_that_cannot_be_read_is_no_figures_logged(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """A report path the service cannot read (a directory here; in the image, which runs
    as an unprivileged user, a mounted file it may not read) was a 500 on every
    GET /v1/decoders: only a missing file or a bad report's content was caught."""
    with caplog.at_level(logging.WARNING, logger="models.decoders.measured"):
        assert benchmark_figures(tmp_path) is None
    assert f"{tmp_path} is a directory" in caplog.text
