"""HDR scene sequences the virtual SCAMP-5 looks at (scene-referred irradiance).

:class:`ProceduralScene`: a smooth textured wall seen by a panning camera, a
light blob moving across it, and a triangular brightness ramp; values are in
scene units where 1 is a mid-bright surface at gain 1. :class:`ExrScene`: a
window panning across the luminance of one or more HDR files. Both are pure
functions of the frame index, so a test can re-render any frame.
"""

from __future__ import annotations

from collections.abc import Sequence
from functools import cached_property
from pathlib import Path
from typing import Protocol

import numpy as np
from numpy.typing import NDArray

from models.errors import InvalidInputError
from models.exposure import luminance

#: Sensor side in pixels (SCAMP-5: 256 x 256 processing elements).
SENSOR_SIZE = 256


class SceneSequence(Protocol):
    """A sequence of grayscale scenes, ``H x W`` float64 irradiance per frame index."""

    def render(self, index: int) -> NDArray[np.float64]:
        """The scene at frame ``index`` (scene units, non-negative)."""
        ...


class ProceduralScene:
    """Pan + moving light + brightness ramp; smooth enough for phase-unwrapping decoders.

    ``light_peak``: peak irradiance added by the light (scene units);
    ``pan_px``: camera pan per frame in pixels; ``ramp_frames``: period of the
    brightness ramp between ``0.5x`` and ``1.5x``.
    """

    def __init__(self, size: int = SENSOR_SIZE, light_peak: float = 6.0, pan_px: float = 1.0,
                 ramp_frames: int = 240, light_sigma_px: float = 28.0) -> None:
        self.size = size
        self.light_peak = light_peak
        self.pan_px = pan_px
        self.ramp_frames = ramp_frames
        self.light_sigma_px = light_sigma_px

    @cached_property
    def _grid(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        axis = np.arange(self.size, dtype=np.float64)
        return np.meshgrid(axis, axis, indexing="xy")

    def brightness(self, index: int) -> float:
        """Global brightness factor at frame ``index``: a triangle wave in [0.5, 1.5]."""
        phase = (index % self.ramp_frames) / self.ramp_frames
        return 0.5 + 2.0 * min(phase, 1.0 - phase)

    def render(self, index: int) -> NDArray[np.float64]:
        """The scene at frame ``index`` (scene units)."""
        xx, yy = self._grid
        u = xx + self.pan_px * index
        wall = 0.55 + 0.25 * np.sin(u / 23.0) * np.cos(yy / 31.0) + 0.15 * np.sin(
            (u + 2.0 * yy) / 41.0
        )
        centre_x = self.size * (0.5 + 0.35 * np.sin(index / 37.0))
        centre_y = self.size * (0.5 + 0.25 * np.cos(index / 53.0))
        light = self.light_peak * np.exp(
            -((xx - centre_x) ** 2 + (yy - centre_y) ** 2) / (2.0 * self.light_sigma_px**2)
        )
        return self.brightness(index) * (wall + light)


class ExrScene:
    """A ``size x size`` window panning across the luminance of HDR images, one per frame."""

    def __init__(self, paths: Sequence[Path], size: int = SENSOR_SIZE,
                 pan_px: int = 1) -> None:
        if not paths:
            raise InvalidInputError("give at least one HDR image for the scene")
        from models.hdr_io import read_hdr

        self.images = [luminance(read_hdr(Path(p), clip_negative=True).pixels) for p in paths]
        small = [img.shape for img in self.images if min(img.shape) < size]
        if small:
            raise InvalidInputError(
                f"HDR images must be at least {size} x {size} pixels, got {small}"
            )
        self.size = size
        self.pan_px = pan_px

    def render(self, index: int) -> NDArray[np.float64]:
        """Frame ``index``: image ``index mod n``, window shifted ``pan_px`` per frame."""
        image = self.images[index % len(self.images)]
        span = image.shape[1] - self.size
        step = (index * self.pan_px) % (2 * span) if span else 0
        left = step if step <= span else 2 * span - step
        top = (image.shape[0] - self.size) // 2
        window = image[top : top + self.size, left : left + self.size]
        return np.maximum(window, 0.0)
