"""8-bit previews for the web viewer: tonemapped HDR, colour-coded W, wrapped codes, histogram.

Previews are for looking at, not for measuring: the EXR and the ``npy`` W map
are the results. The tonemap is an exposure (``x * 2^EV``), a clip to [0, 1]
and the sRGB transfer curve.
"""

from __future__ import annotations

import io
from typing import Any

import numpy as np
from numpy.typing import NDArray
from PIL import Image

from models.display import srgb8
from models.exposure import luminance

#: Colours of W = 0, 1, 2, ... (cycled): dark to bright, neighbours clearly distinct.
WINDING_PALETTE = np.array(
    [
        (20, 20, 40),
        (59, 82, 139),
        (33, 145, 140),
        (94, 201, 98),
        (253, 231, 37),
        (245, 130, 48),
        (220, 50, 47),
        (145, 30, 180),
    ],
    dtype=np.uint8,
)
HISTOGRAM_BINS = 64


def png_bytes(pixels: NDArray[np.uint8]) -> bytes:
    """An 8-bit PNG (grey for H x W, and for the H x W x 1 of a frame stored so, which
    Pillow makes no image of; RGB for H x W x 3)."""
    if pixels.ndim == 3 and pixels.shape[2] == 1:
        pixels = pixels[:, :, 0]
    buffer = io.BytesIO()
    Image.fromarray(np.ascontiguousarray(pixels)).save(buffer, format="PNG")
    return buffer.getvalue()


def scene_to_wrap_units(
    pixels: NDArray[np.float64], gain: float | None
) -> NDArray[np.float64]:
    """Scene-referred pixels (x / gain, as results are stored when the gain is known)
    back in wrap units, the scale every preview and its exposure slider share."""
    return pixels * gain if gain is not None else pixels


def tonemap_png(x: NDArray[np.floating], exposure_ev: float) -> bytes:
    """Preview of linear HDR ``x`` (wrap units: 1 = a conventional pixel's saturation)."""
    return png_bytes(srgb8(np.asarray(x, dtype=np.float64) * 2.0**exposure_ev))


def winding_png(winding: NDArray[np.integer]) -> bytes:
    """W colour-coded by :data:`WINDING_PALETTE` (a colour frame: per-channel colours
    are blended as the mean W of the pixel)."""
    w = np.asarray(winding)
    if w.ndim == 3:
        w = np.rint(w.mean(axis=2)).astype(np.int64)
    index = np.mod(np.maximum(w, 0), len(WINDING_PALETTE))
    return png_bytes(WINDING_PALETTE[index])


def codes_png(codes: NDArray[np.integer], bits: int) -> bytes:
    """Wrapped codes scaled to 0..255 (the sawtooth a wrapping sensor records)."""
    scaled = np.asarray(codes, dtype=np.float64) * (255.0 / ((1 << bits) - 1))
    return png_bytes(np.round(scaled).astype(np.uint8))


def log_luminance_histogram(x: NDArray[np.floating], bins: int = HISTOGRAM_BINS) -> dict[str, Any]:
    """Histogram of log10 luminance of the pixels with positive luminance."""
    lum = luminance(x).ravel()
    positive = lum[lum > 0]
    if positive.size == 0:
        return {"log10_edges": [], "counts": [], "zero_pixels": int(lum.size)}
    logs = np.log10(positive)
    low, high = float(logs.min()), float(logs.max())
    counts, edges = np.histogram(logs, bins=bins, range=(low, max(high, low + 1e-6)))
    return {
        "log10_edges": [float(e) for e in edges],
        "counts": [int(c) for c in counts],
        "zero_pixels": int(lum.size - positive.size),
    }
