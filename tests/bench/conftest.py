"""Shared fixtures of the benchmark tests."""

from __future__ import annotations

from pathlib import Path

import pytest

import bench
from bench import tradeoff


@pytest.fixture(autouse=True)
def reports_in_tmp(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """Point the benchmarks' default report folder at ``tmp_path``: a test that runs a
    benchmark without ``--out`` (one whose refusal stopped working, say) must not
    overwrite the committed reports in bench/results/."""
    monkeypatch.setattr(bench, "RESULTS", tmp_path)
    monkeypatch.setattr(tradeoff, "RESULTS", tmp_path)
    return tmp_path
