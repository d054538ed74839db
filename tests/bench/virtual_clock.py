"""A clock that only a decoder moves, to check what a benchmark's timing includes without
timing anything: :class:`PricedItoh` spends on each channel what its price says, and
:class:`SlowFirstItoh` 1 s on its first channel (as a net's ONNX session creation does)
and 1 ms on every later one."""

from __future__ import annotations

from collections.abc import Callable

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


class PricedItoh(ItohDecoder):
    """itoh that spends ``price(m)`` ns of ``clock`` on each channel ``m`` it decodes."""

    def __init__(self, clock: VirtualClock, price: Callable[[np.ndarray], int]) -> None:
        self.clock = clock
        self.price = price

    def predict_winding(self, m: np.ndarray, params: SensorParams) -> np.ndarray:
        self.clock.now += self.price(m)
        return super().predict_winding(m, params)


class SlowFirstItoh(PricedItoh):
    """itoh whose first channel decoded costs :data:`FIRST_NS` of ``clock``, every later
    one :data:`LATER_NS`."""

    def __init__(self, clock: VirtualClock) -> None:
        super().__init__(clock, self.first_dearer)
        self.calls = 0

    def first_dearer(self, m: np.ndarray) -> int:
        self.calls += 1
        return FIRST_NS if self.calls == 1 else LATER_NS
