"""A clock that only a decoder moves, to check what a benchmark's timing includes without
timing anything: :class:`SlowFirstItoh` spends 1 s of it on its first frame (as a net's
ONNX session creation does) and 1 ms on every later one."""

from __future__ import annotations

import numpy as np

from models.decoders.classical import ItohDecoder
from models.formation import SensorParams

#: Virtual ns the first frame and every later frame cost.
FIRST_NS = 10**9
LATER_NS = 10**6


class VirtualClock:
    """Nanoseconds that pass only when a decoder spends them; call it for the time."""

    def __init__(self) -> None:
        self.now = 0

    def __call__(self) -> int:
        return self.now


class SlowFirstItoh(ItohDecoder):
    """itoh whose first channel decoded costs :data:`FIRST_NS` of ``clock``, every later
    one :data:`LATER_NS`."""

    def __init__(self, clock: VirtualClock) -> None:
        self.clock = clock
        self.calls = 0

    def predict_winding(self, m: np.ndarray, params: SensorParams) -> np.ndarray:
        self.clock.now += FIRST_NS if self.calls == 0 else LATER_NS
        self.calls += 1
        return super().predict_winding(m, params)
