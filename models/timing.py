"""Wall-clock timing of a repeated call, shared by the runtime's calibration and the benchmarks."""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

import numpy as np


def median_ns(call: Callable[[], Any], repeats: int) -> float:
    """Median wall time of ``call()`` in ns over ``repeats`` calls, after one warm-up call."""
    return float(np.median(wall_times_ns(call, repeats)))


def fastest_ns(call: Callable[[], Any], repeats: int) -> float:
    """Least wall time of ``call()`` in ns over ``repeats`` calls, after one warm-up call:
    its cost with the least interference from other load."""
    return float(np.min(wall_times_ns(call, repeats)))


def wall_times_ns(call: Callable[[], Any], repeats: int) -> list[int]:
    """Wall times of ``repeats`` calls of ``call()`` in ns, after one warm-up call."""
    call()
    times = []
    for _ in range(repeats):
        start = time.perf_counter_ns()
        call()
        times.append(time.perf_counter_ns() - start)
    return times
