"""The synthetic video benchmark set: seeded wrapped clips with exact per-frame truth.

Four kinds of motion, each over a 360-degree HDR panorama from ``models/data/hdri``
(read by :func:`models.scenes.load_hdri_gray`, luminance only):

- ``pan_zoom``: a camera pans across the panorama (wrapping at the seam) while
  zooming in (the crop shrinks from the full frame to ``ZOOM_END`` of it);
- ``moving_light``: a static view with a very bright Gaussian light source moving
  on an ellipse (its peak is ``LIGHT_PEAK`` times the view's 99th percentile);
- ``sunrise``: a static view under a global brightness ramp of ``SUNRISE_STOPS``
  stops, so wraps sweep across the frame and in the end nearly every pixel wraps;
- ``static_noise``: a static view whose only change is sensor noise (pure flicker).

Frames are made only by :func:`models.formation.simulate`: one fixed gain per clip
and encoding (``OVEREXPOSED`` of the middle frame's pixels exceed one wrap), the
noise seeded per frame. Ground truth per frame and encoding: the exact ``x`` (wrap
units, after ``max_wraps``) and the winding numbers ``W`` the pixels really made
(noise included). Scene-referred values are the view's luminance (any scale).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.ndimage import map_coordinates

from models.errors import InvalidInputError
from models.exposure import exposure_gain
from models.formation import SensorParams, simulate
from models.scenes import load_hdri_gray

CLIP_KINDS: tuple[str, ...] = ("pan_zoom", "moving_light", "sunrise", "static_noise")
#: The panorama each kind looks at.
CLIP_SCENES: dict[str, str] = {
    "pan_zoom": "city",
    "moving_light": "hall",
    "sunrise": "dawn",
    "static_noise": "studio",
}
VIDEO_ENCODINGS: tuple[str, ...] = ("mantissa", "modulo")
DEFAULT_FRAMES = 60
DEFAULT_SIZE = 256
OVEREXPOSED = 0.2
MAX_WRAPS = 16.0
#: Pan speed in panorama pixels per frame; final crop side as a fraction of the first.
PAN_SPEED = 1.5
ZOOM_END = 0.7
LIGHT_PEAK = 200.0
LIGHT_SIGMA = 6.0
SUNRISE_STOPS = 8.0
#: Sensor noise of every clip (read noise sigma in wraps, full-well electrons at x = 1)
#: and the stronger noise of the static clip.
READ_NOISE = 0.002
FULL_WELL = 20_000.0
STATIC_READ_NOISE = 0.01
STATIC_FULL_WELL = 2_000.0


@dataclass(frozen=True)
class ClipEncoding:
    """One clip seen through one sensor encoding, T frames.

    ``params``: the shared sensor parameters (with the clip's gain; the per-frame
    noise seeds are not kept); ``codes``: T x H x W (DN); ``winding``: the true
    W, T x H x W int64; ``irradiance``: the true ``x``, T x H x W float64 (wrap units).
    """

    params: SensorParams
    codes: NDArray[np.unsignedinteger]
    winding: NDArray[np.int64]
    irradiance: NDArray[np.float64]


@dataclass(frozen=True)
class VideoClip:
    """A seeded clip: its name, the scene-referred frames (T x H x W) and its encodings."""

    name: str
    scene: NDArray[np.float64]
    encodings: dict[str, ClipEncoding]

    @property
    def frames(self) -> int:
        """Number of frames T."""
        return int(self.scene.shape[0])


def _sample(image: NDArray[np.float64], rows: NDArray, cols: NDArray) -> NDArray[np.float64]:
    """Bilinear samples of ``image`` at fractional (row, col) pixel indices: columns wrap
    around (a 360-degree panorama, the last column next to the first), rows outside
    0..H-1 take the edge row."""
    seamless = np.concatenate([image, image[:, :1]], axis=1)
    cols = np.mod(cols, image.shape[1])
    return map_coordinates(seamless, [rows, cols], order=1, mode="nearest")


def _centre_view(panorama: NDArray[np.float64], size: int) -> NDArray[np.float64]:
    """The ``size x size`` view at the panorama's centre (whole pixels, no resampling);
    a view taller than the panorama repeats its top and bottom rows."""
    top = (panorama.shape[0] - size) // 2
    left = (panorama.shape[1] - size) // 2
    grid = np.mgrid[top : top + size, left : left + size].astype(np.float64)
    return _sample(panorama, grid[0], grid[1])


def pan_zoom_frames(panorama: NDArray[np.float64], frames: int, size: int) -> NDArray[np.float64]:
    """The camera pans right by ``PAN_SPEED`` px/frame while its crop shrinks to ``ZOOM_END``."""
    side0 = min(panorama.shape[0], size)
    centre_row = (panorama.shape[0] - 1) / 2
    steps = np.linspace(0.0, 1.0, size)
    out = np.empty((frames, size, size))
    for t in range(frames):
        side = side0 * (1.0 - (1.0 - ZOOM_END) * t / max(frames - 1, 1))
        offsets = (steps - 0.5) * (side - 1)
        centre_col = panorama.shape[1] / 2 + PAN_SPEED * t
        rows, cols = np.meshgrid(centre_row + offsets, centre_col + offsets, indexing="ij")
        out[t] = _sample(panorama, rows, cols)
    return out


def moving_light_frames(view: NDArray[np.float64], frames: int) -> NDArray[np.float64]:
    """A Gaussian light (peak ``LIGHT_PEAK`` x the view's 99th percentile) moving on an ellipse."""
    size = view.shape[0]
    peak = LIGHT_PEAK * float(np.percentile(view, 99))
    yy, xx = np.mgrid[0:size, 0:size].astype(np.float64)
    out = np.empty((frames, *view.shape))
    for t in range(frames):
        phase = 2 * np.pi * t / frames
        cy = size / 2 + 0.3 * size * np.sin(phase)
        cx = size / 2 + 0.35 * size * np.cos(phase)
        light = np.exp(-((yy - cy) ** 2 + (xx - cx) ** 2) / (2 * LIGHT_SIGMA**2))
        out[t] = view + peak * light
    return out


def sunrise_frames(view: NDArray[np.float64], frames: int) -> NDArray[np.float64]:
    """The view under a brightness ramp from -SUNRISE_STOPS/2 to +SUNRISE_STOPS/2 stops."""
    stops = np.linspace(-SUNRISE_STOPS / 2, SUNRISE_STOPS / 2, frames)
    return view[None] * (2.0**stops)[:, None, None]


def static_frames(view: NDArray[np.float64], frames: int) -> NDArray[np.float64]:
    """The same view in every frame."""
    return np.repeat(view[None], frames, axis=0)


def clip_scene(kind: str, frames: int = DEFAULT_FRAMES, size: int = DEFAULT_SIZE) -> NDArray:
    """Scene-referred luminance frames (T x size x size) of clip ``kind``."""
    if kind not in CLIP_KINDS:
        raise InvalidInputError(f"unknown clip {kind!r}; choose one of: {', '.join(CLIP_KINDS)}")
    if frames < 2 or size < 2:
        raise InvalidInputError(f"a clip needs at least 2 frames of 2 x 2, got {frames} x {size}")
    panorama = load_hdri_gray(CLIP_SCENES[kind])
    if kind == "pan_zoom":
        return pan_zoom_frames(panorama, frames, size)
    view = _centre_view(panorama, size)
    if kind == "moving_light":
        return moving_light_frames(view, frames)
    if kind == "sunrise":
        return sunrise_frames(view, frames)
    return static_frames(view, frames)


def clip_params(kind: str, encoding: str) -> SensorParams:
    """Sensor parameters of a clip before exposure: 8 bits, alpha 2, ``MAX_WRAPS``, noise."""
    static = kind == "static_noise"
    values: dict[str, Any] = {
        "encoding": encoding,
        "bits": 8,
        "alpha": 2.0,
        "max_wraps": MAX_WRAPS,
        "read_noise": STATIC_READ_NOISE if static else READ_NOISE,
        "full_well": STATIC_FULL_WELL if static else FULL_WELL,
    }
    return SensorParams.parse(values)


def encode_clip(
    scene: NDArray[np.float64], params: SensorParams, seed: int
) -> ClipEncoding:
    """Expose every frame with one gain (from the middle frame) and encode it, seeded per frame."""
    gain = exposure_gain(scene[scene.shape[0] // 2], OVEREXPOSED)
    params = params.model_copy(update={"gain": gain, "seed": None})
    codes, winding, irradiance = [], [], []
    for t, frame in enumerate(scene):
        sensor = simulate(frame, params.model_copy(update={"seed": seed * 100_003 + t}))
        codes.append(sensor.codes)
        winding.append(sensor.winding)
        irradiance.append(sensor.irradiance)
    return ClipEncoding(params, np.stack(codes), np.stack(winding), np.stack(irradiance))


def make_clip(
    kind: str,
    *,
    frames: int = DEFAULT_FRAMES,
    size: int = DEFAULT_SIZE,
    seed: int = 0,
    encodings: tuple[str, ...] = VIDEO_ENCODINGS,
) -> VideoClip:
    """Clip ``kind`` (see :data:`CLIP_KINDS`) with its ground truth for each encoding."""
    scene = clip_scene(kind, frames, size)
    encoded = {
        enc: encode_clip(scene, clip_params(kind, enc), seed * len(CLIP_KINDS) + index)
        for index, enc in enumerate(encodings)
    }
    return VideoClip(kind, scene, encoded)
