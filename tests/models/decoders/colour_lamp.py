"""A colour frame of a clipped lamp, for tests of how a colour frame's clips are filled."""

from __future__ import annotations

import numpy as np

from models.formation import SensorFrame, SensorParams, dequantize, encode

#: Mantissa, 8 bits, clipped at 16 wraps (``u_max`` 5, code 0).
PARAMS = SensorParams(encoding="mantissa", bits=8, max_wraps=16.0, seed=3)
#: White: every channel clipped over the lamp's core.
WHITE = (1.0, 1.0, 1.0)


def colour_lamp(
    tint: tuple[float, float, float] = WHITE,
    size: int = 128,
    peak: float = 200.0,
    dark: bool = False,
) -> tuple[SensorFrame, np.ndarray, np.ndarray]:
    """A :data:`PARAMS` frame of a lamp (Gaussian, sigma 4 px, at the centre) of colour
    ``tint`` (``peak`` wraps times each channel's share) on a dark background (0.1-1.1
    wraps) textured differently in each channel, black with ``dark``; its ``m`` (wraps)
    and its clipped pixel-channels (H x W x 3). The defaults are a white lamp whose
    core auto-fast's net called dark in red and green and bright in blue."""
    yy, xx = np.mgrid[0:size, 0:size].astype(np.float64)
    centre = size / 2
    lamp = peak * np.exp(-((yy - centre) ** 2 + (xx - centre) ** 2) / (2 * 4.0**2))
    textures = [
        (1.0 - 0.1 * c) * (0.6 + 0.5 * np.sin(xx / (3 + c)) * np.cos(yy / (5 - c)))
        for c in range(3)
    ]
    planes = [
        share * lamp + (0.0 if dark else texture)
        for share, texture in zip(tint, textures, strict=True)
    ]
    frame = encode(np.stack(planes, axis=2), PARAMS)
    return frame, dequantize(frame.codes, PARAMS.bits), frame.irradiance >= PARAMS.max_wraps
