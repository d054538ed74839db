"""Tests of bench/tradeoff.py: the Pareto front and a tiny end-to-end run (no timings asserted)."""

from __future__ import annotations

import json
from pathlib import Path

from bench import tradeoff


def test_pareto_marks_only_undominated_rows() -> None:
    rows = [
        {"decoder": "fast-bad", "ms_per_frame": 1.0, "psnr_db": 20.0},
        {"decoder": "slow-good", "ms_per_frame": 10.0, "psnr_db": 40.0},
        {"decoder": "dominated", "ms_per_frame": 12.0, "psnr_db": 30.0},
        {"decoder": "twin", "ms_per_frame": 10.0, "psnr_db": 40.0},
    ]
    tradeoff.pareto(rows)
    assert [r["pareto"] for r in rows] == [True, True, False, True]


def test_quick_run_writes_json_markdown_and_plot(tmp_path: Path) -> None:
    out = tmp_path / "tradeoff.json"
    plot = tmp_path / "tradeoff.png"
    tradeoff.main(
        ["--quick", "--frames", "1", "--dark", "1", "--repeats", "1", "--decoders", "itoh",
         "auto-fast", "--out", str(out), "--plot", str(plot)]
    )  # fmt: skip
    report = json.loads(out.read_text())
    assert set(report["results"]) == {"val-256", "mostly-dark"}
    decoders = {r["decoder"] for r in report["results"]["val-256"]}
    assert decoders == {"itoh", "auto-fast"}
    assert report["peak_gflops_per_s"] > 0
    assert plot.read_bytes()[:4] == b"\x89PNG"
    assert "| itoh |" in out.with_suffix(".md").read_text()
