"""Tests of bench/service.py's report: the Markdown names the date, machine and load."""

from __future__ import annotations

from typing import Any

from bench import service


def report() -> dict[str, Any]:
    stages = {"queue_wait": 1.5, "decode": 1.7, "encode": 3.8, "total": 8.6, "api_http": 6.3}
    level = {
        "clients": 1, "jobs": 10, "jobs_per_s": 61.4, "p50_ms": 14.8, "p99_ms": 22.2,
        "lost": 0, "median_stage_ms": stages,
    }  # fmt: skip
    return {
        "date": "2026-11-27T00:13:14+00:00",
        "machine": {"cpu": "AMD EPYC", "cores": 2},
        "load_average": (0.981, 1.14, 1.03),
        "decoder": "itoh",
        "size": "256x256",
        "in_process_decode_ms": 1.2,
        "overhead_ms": 13.6,
        "overhead_pct": 1133.0,
        "levels": [level],
    }


def test_markdown_names_date_machine_and_load_and_has_a_row_per_level() -> None:
    text = service.markdown(report())
    head, _, *rows = text.splitlines()
    assert "2026-11-27T00:13:14+00:00" in head
    assert "AMD EPYC (2 cores)" in head
    assert "load average at the end [0.98, 1.14, 1.03]" in head
    assert rows[-1].startswith("| 1 | 10 | 61.4 | 14.8 | 22.2 | 0 | queue_wait 1.5")
    assert len(rows) == 3


def test_a_lost_request_counts_in_neither_jobs_per_second_nor_latency() -> None:
    """A refused or failed request, answered at once, counted as a job done: it raised
    jobs/s and lowered the percentiles."""
    outcomes = [
        (0.020, {"state": "succeeded", "timings_ns": {"total": 10_000_000}}),
        (0.001, {"state": "failed", "timings_ns": {"total": 500_000}}),
        (0.001, {"error": {"code": "rate_limited"}}),
    ]
    level = service.level_figures(4, outcomes, elapsed_s=0.5)
    assert level["jobs"] == 3 and level["lost"] == 2
    assert level["jobs_per_s"] == 2.0
    assert level["p50_ms"] == level["p99_ms"] == 20.0


def test_a_level_where_no_job_succeeded_shows_no_latency() -> None:
    level = service.level_figures(1, [(0.001, {"state": "failed"})], elapsed_s=0.5)
    assert level["p50_ms"] is None and level["jobs_per_s"] == 0.0
    result = {**report(), "levels": [level], "overhead_ms": None, "overhead_pct": None}
    text = service.markdown(result)
    assert "overhead at 1 client none measured (no job succeeded)" in text
    assert text.splitlines()[-1].startswith("| 1 | 1 | 0.0 | - | - | 1 |")
