"""A decoder made to fill clipped blobs (:func:`models.decoders.saturation.fill_saturated`)
as ``auto`` does: what a stream decoding along time uses when its spatial decoder does
not fill them (:mod:`worker.temporal`). Like ``auto`` it fills a colour frame's clip in
every channel that holds it before the channels are joined (:func:`filled_then_joined`)."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np
from numpy.typing import NDArray

from models.decoders.base import Decoder
from models.decoders.saturation import fill_saturated, fill_shared
from models.formation import SensorParams

#: What a decoder does with a colour frame's channels once each is decoded
#: (:meth:`models.decoders.base.Decoder.join_channels`): (m, W, params) -> W, facts.
Join = Callable[
    [NDArray[np.float64], NDArray[np.int64], SensorParams],
    tuple[NDArray[np.int64], dict[str, Any]],
]


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
        """A colour frame's clips filled in every channel that holds them
        (:func:`filled_then_joined`), then ``inner``'s way with its channels."""
        return filled_then_joined(planes, winding, params, self.inner.join_channels)

    def run_pixels(self, shape: tuple[int, int], params: SensorParams) -> list[int]:
        return self.inner.run_pixels(shape, params)


def filling(decoder: Decoder) -> Decoder:
    """``decoder`` itself when it fills clipped blobs, else it wrapped to fill them."""
    return decoder if decoder.fills_saturation else FillingDecoder(decoder)


def filled_then_joined(
    planes: NDArray[np.float64],
    winding: NDArray[np.int64],
    params: SensorParams,
    join: Join,
) -> tuple[NDArray[np.int64], dict[str, Any]]:
    """A colour frame's W (H x W x C; ``planes`` its ``m``, wraps) with each clip filled
    in every channel that holds it (:func:`models.decoders.saturation.fill_shared`), then
    ``join(planes, winding, params)``; the join's facts, with the fill's under
    ``saturation`` when some channel holds a saturated blob."""
    winding, shared = fill_shared(winding, planes, params)
    winding, joined = join(planes, winding, params)
    return winding, ({**joined, "saturation": shared} if shared else joined)
