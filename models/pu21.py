"""PU21 perceptually uniform encoding of absolute luminance (Mantiuk & Azimi, PCS 2021).

The 'banding_glare' variant, the one its authors recommend, with the parameters of
their reference implementation (gfxdisp/pu21, ``pu21_encoder.m``, updated 06/02/2020):

    V = max(p7 * (((p1 + p2 * Y^p4) / (1 + p3 * Y^p4))^p5 - p6), 0)

``Y`` is absolute luminance in cd/m^2, clamped to [0.005, 10000]; ``V`` is in PU
units, from 0 (at 0.005 cd/m^2) to about 595 (at 10000 cd/m^2), with 100 cd/m^2
mapped close to 256 to mimic the input range of SDR quality metrics.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from models.errors import InvalidInputError

#: 'banding_glare' parameters p1..p7 of the reference implementation.
BANDING_GLARE = (
    0.353487901,
    0.3734658629,
    8.277049286e-05,
    0.9062562627,
    0.09150303166,
    0.9099517204,
    596.3148142,
)
#: Luminance range of the encoding, cd/m^2.
L_MIN = 0.005
L_MAX = 10000.0


def pu21_encode(luminance: ArrayLike) -> NDArray[np.float64]:
    """PU21 value of absolute luminance (cd/m^2), clamped to [L_MIN, L_MAX] first; NaN
    is refused (the clamp would pass it through)."""
    p1, p2, p3, p4, p5, p6, p7 = BANDING_GLARE
    values = np.asarray(luminance, dtype=np.float64)
    if np.isnan(values).any():
        raise InvalidInputError(
            f"PU21 encodes luminance in cd/m^2: {int(np.isnan(values).sum())} values are NaN"
        )
    y = np.clip(values, L_MIN, L_MAX) ** p4
    return np.maximum(p7 * (((p1 + p2 * y) / (1.0 + p3 * y)) ** p5 - p6), 0.0)


def pu21_decode(value: ArrayLike) -> NDArray[np.float64]:
    """Absolute luminance (cd/m^2) of a PU21 value: the inverse of :func:`pu21_encode`,
    the value clamped to the encoding's range [0, :data:`PU21_PEAK`] first (past it the
    inverse is NaN or above L_MAX); NaN is refused."""
    p1, p2, p3, p4, p5, p6, p7 = BANDING_GLARE
    values = np.asarray(value, dtype=np.float64)
    if np.isnan(values).any():
        raise InvalidInputError(f"PU21 values: {int(np.isnan(values).sum())} are NaN")
    v = np.maximum(np.clip(values, 0.0, PU21_PEAK) / p7 + p6, 0.0) ** (1.0 / p5)
    return (np.maximum(v - p1, 0.0) / (p2 - p3 * v)) ** (1.0 / p4)


#: PU21 value of the brightest encodable luminance: the peak of PU21-PSNR.
PU21_PEAK = float(pu21_encode(L_MAX))
