"""A seeded smooth scene and a camera pan over it: shared by the motion and temporal tests."""

from __future__ import annotations

import numpy as np
from scipy.ndimage import gaussian_filter

from models.formation import SensorFrame, SensorParams, encode

PAN_PARAMS = SensorParams(encoding="modulo", bits=10)


def smooth_scene(rows: int = 64, cols: int = 128, scale: float = 3.0, seed: int = 3) -> np.ndarray:
    """Seeded smooth texture, ``0.05 + scale * t^2`` wraps (t in [0, 1]), periodic in x:
    at scale 3 its steepest step is 0.44 wraps/px (Itoh decodes it exactly), so a
    2 px/frame pan changes u at a pixel by up to 0.9 wraps (the plain temporal rule aliases)."""
    noise = np.random.default_rng(seed).standard_normal((rows, cols))
    canvas = gaussian_filter(noise, 4.0, mode="wrap")
    canvas = (canvas - canvas.min()) / (canvas.max() - canvas.min())
    return 0.05 + scale * canvas**2


def pan_clip(
    frames: int, speed: int = 2, size: tuple[int, int] = (64, 64), gain: float = 1.0
) -> list[SensorFrame]:
    """``frames`` noiseless modulo frames of a ``size`` view panning right by ``speed``
    px/frame while the light grows by ``gain`` per frame."""
    scene = smooth_scene()
    return [
        encode(gain**t * np.roll(scene, -speed * t, axis=1)[: size[0], : size[1]], PAN_PARAMS)
        for t in range(frames)
    ]
