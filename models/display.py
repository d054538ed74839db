"""Display encodings shared by the still previews and the SDR video: the sRGB transfer
curve (IEC 61966-2-1) from linear display values in [0, 1] to 8-bit codes (DN)."""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from models.errors import InvalidInputError


def srgb8(linear: ArrayLike) -> NDArray[np.uint8]:
    """Linear display values (clipped to [0, 1]) through the sRGB transfer curve, as 8-bit
    codes 0..255; NaN is refused (the clip passed it on, and it came out black)."""
    values = np.asarray(linear, dtype=np.float64)
    if np.isnan(values).any():
        raise InvalidInputError(
            f"sRGB encodes linear values in [0, 1]: {int(np.isnan(values).sum())} are NaN"
        )
    v = np.clip(values, 0.0, 1.0)
    encoded = np.where(v <= 0.0031308, 12.92 * v, 1.055 * np.power(v, 1 / 2.4) - 0.055)
    return np.round(encoded * 255.0).astype(np.uint8)
