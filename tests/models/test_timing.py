"""Tests of models/timing.py: a warm-up call, then the median of the timed calls."""

from __future__ import annotations

import time

from models.timing import median_ns


def test_calls_once_more_than_timed_and_measures_the_sleep() -> None:
    calls = []

    def nap() -> None:
        calls.append(1)
        time.sleep(0.002)

    elapsed = median_ns(nap, 3)
    assert len(calls) == 4
    assert elapsed >= 2e6
