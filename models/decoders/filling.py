"""A decoder made to fill clipped blobs (:func:`models.decoders.saturation.fill_saturated`)
as ``auto`` does: what a stream decoding along time uses when its spatial decoder does
not fill them (:mod:`worker.temporal`)."""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

from models.decoders.base import Decoder
from models.decoders.saturation import fill_saturated
from models.formation import SensorParams


class FillingDecoder(Decoder):
    """``inner``'s W with every clipped blob set to the sensor's clip, and ``inner``'s
    facts with the fill's (``saturation``). It keeps ``inner``'s name, version, the
    encodings it unwraps, what it does with a colour frame's channels and its runs."""

    fills_saturation = True

    def __init__(self, inner: Decoder) -> None:
        self.inner = inner
        self.name = inner.name  # type: ignore[misc]
        self.version = inner.version

    def unwraps(self, params: SensorParams) -> bool:
        return self.inner.unwraps(params)

    def predict_winding(self, m: NDArray[np.float64], params: SensorParams) -> NDArray[np.int64]:
        return self.explain_winding(m, params)[0]

    def explain_winding(
        self, m: NDArray[np.float64], params: SensorParams
    ) -> tuple[NDArray[np.int64], dict[str, Any]]:
        """``inner``'s W (H x W) and facts, the clipped blobs of ``m`` (wraps) filled."""
        winding, facts = self.inner.explain_winding(m, params)
        winding, saturation = fill_saturated(winding, m, params)
        if saturation:
            facts = {**facts, "saturation": saturation}
        return winding, facts

    def join_channels(
        self, planes: NDArray[np.float64], winding: NDArray[np.int64], params: SensorParams
    ) -> tuple[NDArray[np.int64], dict[str, Any]]:
        return self.inner.join_channels(planes, winding, params)

    def run_pixels(self, shape: tuple[int, int], params: SensorParams) -> list[int]:
        return self.inner.run_pixels(shape, params)


def filling(decoder: Decoder) -> Decoder:
    """``decoder`` itself when it fills clipped blobs, else it wrapped to fill them."""
    return decoder if decoder.fills_saturation else FillingDecoder(decoder)
