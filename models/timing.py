"""Wall-clock timing of a repeated call, shared by the runtime's calibration and the benchmarks."""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

import numpy as np


def median_ns(call: Callable[[], Any], repeats: int) -> float:
    """Median wall time of ``call()`` in ns over ``repeats`` calls, after one warm-up call."""
    call()
    times = []
    for _ in range(repeats):
        start = time.perf_counter_ns()
        call()
        times.append(time.perf_counter_ns() - start)
    return float(np.median(times))
