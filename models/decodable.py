"""Whether a frame's codes can decode at all: the error :func:`models.formation.reconstruct`
would raise whatever winding numbers a decoder finds, raised before any decoding
(:func:`check_decodable`), from the largest W a decoding may hold
(:func:`largest_winding`)."""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

from models.errors import OutputOverflowError, OutputUnderflowError
from models.formation import MAX_WINDING, SensorParams, max_winding, reconstruct


def largest_winding(params: SensorParams) -> int:
    """The largest W a decoding of a frame of ``params`` may hold: :func:`max_winding` where
    the parameters bound it, and at most the encoding's own limit: int64's (modulo, whose
    x = W + m float64 holds; a modulo ``max_wraps`` of 2^63 or more bounds W past it) or,
    for mantissa, a wrap below the last whose x ``alpha^(W + m - 1)`` float64 holds."""
    if params.encoding == "modulo":
        limit = int(MAX_WINDING)
    else:
        limit = int(np.log(np.finfo(np.float64).max) / np.log(params.alpha)) - 1
    bound = max_winding(params)
    return limit if bound is None else min(bound, limit)


def check_decodable(
    codes: NDArray[Any],
    params: SensorParams,
    dtype: type[np.floating],
    *,
    scene_referred: bool,
) -> None:
    """Raise, before any decoding, the error :func:`reconstruct` would raise whatever
    winding numbers a decoder finds. x grows with W (W >= 0), so values that exceed
    ``dtype`` at W = 0 exceed it at every W (:class:`OutputOverflowError`: a gain far too
    small, say), and values ``dtype`` stores as 0 at :func:`largest_winding` are lost at
    every W (:class:`OutputUnderflowError`: a gain far too large)."""
    certain = ((0, OutputOverflowError), (largest_winding(params), OutputUnderflowError))
    for winding, error in certain:
        try:
            reconstruct(codes, np.full(np.shape(codes), winding, np.int64), params, dtype,
                        scene_referred=scene_referred)  # fmt: skip
        except error as exc:
            raise error(f"whatever winding numbers a decoder finds, {exc.message}") from None
        except (OutputOverflowError, OutputUnderflowError):
            continue  # another W may fit
