"""A stand-in spatial decoder for tests of what happens after the channels are decoded."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from models.decoders.base import Decoder
from models.formation import SensorParams


class FixedPlanesDecoder(Decoder):
    """Returns the planes of a fixed W (H x W x C), one per call, in channel order."""

    name = "fixed"  # type: ignore[assignment]

    def __init__(self, winding: NDArray[np.int64]) -> None:
        self.winding = winding
        self.calls = 0

    def predict_winding(self, m: NDArray[np.float64], params: SensorParams) -> NDArray[np.int64]:
        plane = self.winding[:, :, self.calls % self.winding.shape[2]]
        self.calls += 1
        return plane.copy()
