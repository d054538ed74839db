"""On-the-fly training pairs ``(m, W)``, made with models.formation only.

A batch mixes random crops of the 14 training HDRIs (random 1x/2x downscale,
wrapping around the panorama seam) and seeded synthetic scenes; each crop gets
random flips and 90-degree rotations, a random exposure (overexposed fraction
0.05..0.35), a random ``max_wraps`` and optionally read noise. Grayscale.
Everything is seeded by ``(seed, step)`` so a resumed run sees the same data.

Saturation-aware pairs (``saturation=True``) add a second input channel, the
pixels whose code could be a clipped pixel's (:func:`models.formation.saturation_candidates`),
and label the truly clipped ones :data:`SATURATED` instead of their W. Half of them
set ``max_wraps`` inside the crop's bright range so that clipped plateaus are common;
half put the clip level on a whole wrap (clip code 0, like ``max_wraps = 16``) and half
paint black patches (code 0 too), so the net learns that a plateau at the clip code can
be dark as well as clipped.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cache

import numpy as np
from numpy.typing import NDArray

from models.errors import InvalidInputError
from models.formation import (
    SensorParams,
    dequantize,
    exposure_gain,
    from_unwrapped,
    saturation_candidates,
    saturation_point,
    simulate,
)
from models.scenes import TRAIN_SCENES, load_hdri_gray, synthetic_scene
from models.training.networks import NUM_CLASSES

OVEREXPOSED_RANGE = (0.05, 0.35)
#: The class of clipped pixels (``x >= max_wraps``) in saturation-aware pairs.
SATURATED = NUM_CLASSES
#: Quantile range, among a crop's wrapped pixels, of the clip level drawn to make plateaus.
CLIP_QUANTILES = (0.5, 0.99)
#: Black patches: how many, their size (fraction of the crop side) and their dimming.
BLACK_PATCHES = (1, 4)
BLACK_SIZE = (0.05, 0.3)
BLACK_DIMMING = (1e-6, 1e-4)


@dataclass(frozen=True)
class PairConfig:
    """What the sampler draws: encoding, crop size (px), batch size and noise range."""

    encoding: str
    crop: int = 64
    batch: int = 8
    max_read_noise: float = 0.0
    synthetic_fraction: float = 0.5
    bits: int = 8
    saturation: bool = False

    @property
    def channels(self) -> int:
        """Input channels: ``m``, plus the saturation candidates when saturation-aware."""
        return 2 if self.saturation else 1


@cache
def _train_scenes() -> tuple[NDArray[np.float64], ...]:
    return tuple(load_hdri_gray(name) for name in TRAIN_SCENES)


def _hdri_crop(rng: np.random.Generator, size: int) -> NDArray[np.float64]:
    """A random ``size x size`` crop of a training HDRI, at 1x or 2x downscale."""
    scene = _train_scenes()[int(rng.integers(len(TRAIN_SCENES)))]
    factor = int(rng.integers(1, 3))
    span = size * factor
    top = int(rng.integers(0, scene.shape[0] - span + 1))
    rows = np.roll(scene[top : top + span], -int(rng.integers(scene.shape[1])), axis=1)
    crop = rows[:, :span]
    return crop.reshape(size, factor, size, factor).mean(axis=(1, 3))


def _augment(rng: np.random.Generator, scene: NDArray[np.float64]) -> NDArray[np.float64]:
    """Random horizontal/vertical flips and a 90-degree rotation."""
    if rng.uniform() < 0.5:
        scene = scene[:, ::-1]
    if rng.uniform() < 0.5:
        scene = scene[::-1]
    return np.ascontiguousarray(np.rot90(scene, int(rng.integers(4))))


def _max_wraps(rng: np.random.Generator, encoding: str) -> float:
    """Modulo: 2..16 wraps; mantissa: 2..4096 (W <= 13 at alpha 2), both < NUM_CLASSES."""
    if encoding == "modulo":
        return float(rng.uniform(2.0, NUM_CLASSES - 1))
    return float(2.0 ** rng.uniform(1.0, 12.0))


def _clip_level(rng: np.random.Generator, x: NDArray[np.float64]) -> float | None:
    """A ``max_wraps`` (wrap units) that clips part of the crop's wrapped pixels (``x``
    already exposed); None when nothing wraps."""
    wrapped = x[x > 1.0]
    if wrapped.size == 0:
        return None
    return max(float(np.quantile(wrapped, rng.uniform(*CLIP_QUANTILES))), 1.0 + 1e-3)


def _sensor_params(rng: np.random.Generator, config: PairConfig) -> SensorParams:
    """Random encoding parameters: ``max_wraps``, read noise (half the crops) and seed."""
    noise = rng.uniform(0.0, config.max_read_noise) if rng.uniform() < 0.5 else 0.0
    return SensorParams(
        encoding=config.encoding,  # type: ignore[arg-type]
        bits=config.bits,
        max_wraps=_max_wraps(rng, config.encoding),
        read_noise=noise,
        seed=int(rng.integers(2**31)),
    )


def _clipping(
    rng: np.random.Generator, params: SensorParams, scene: NDArray[np.float64], overexposed: float
) -> SensorParams:
    """Half the time, the exposure's gain fixed and ``max_wraps`` set to clip the crop."""
    if rng.uniform() < 0.5:
        return params
    gain = exposure_gain(scene, overexposed)
    level = _clip_level(rng, scene * gain)
    if level is None:
        return params
    return params.model_copy(update={"gain": gain, "max_wraps": level})


def _whole_wrap(rng: np.random.Generator, params: SensorParams) -> SensorParams:
    """Half the time, ``max_wraps`` raised to the next whole wrap of ``u`` (clip code 0)."""
    u_sat = saturation_point(params)
    if u_sat is None or rng.uniform() < 0.5:
        return params
    level = float(from_unwrapped(np.array(max(np.ceil(u_sat), 1.0)), params))
    return params.model_copy(update={"max_wraps": level})


def _black_patches(rng: np.random.Generator, scene: NDArray[np.float64]) -> NDArray[np.float64]:
    """Half the time, a few rectangles of the scene dimmed to black (codes 0)."""
    if rng.uniform() < 0.5:
        return scene
    scene = scene.copy()
    size = scene.shape[0]
    for _ in range(int(rng.integers(*BLACK_PATCHES))):
        h, w = (np.maximum(rng.uniform(*BLACK_SIZE, 2) * size, 1)).astype(int)
        top, left = rng.integers(0, size - h + 1), rng.integers(0, size - w + 1)
        scene[top : top + h, left : left + w] *= rng.uniform(*BLACK_DIMMING)
    return scene


def sample_pair(
    rng: np.random.Generator, config: PairConfig
) -> tuple[NDArray[np.float32], NDArray[np.int64]]:
    """One training pair: inputs (float32, ``channels x crop x crop``: ``m``, then the
    saturation candidates when asked) and the target (int64 ``W``, or :data:`SATURATED`)."""
    while True:
        if rng.uniform() < config.synthetic_fraction:
            scene = synthetic_scene(int(rng.integers(2**31)), config.crop)
        else:
            scene = _hdri_crop(rng, config.crop)
        params = _sensor_params(rng, config)
        augmented = _augment(rng, scene)
        overexposed = rng.uniform(*OVEREXPOSED_RANGE)
        if config.saturation:
            augmented = _black_patches(rng, augmented)
            params = _whole_wrap(rng, _clipping(rng, params, augmented, overexposed))
        try:
            frame = simulate(
                augmented, params, overexposed=None if params.gain else overexposed
            )
        except InvalidInputError:
            continue
        m = dequantize(frame.codes, config.bits)
        target = np.minimum(frame.winding, NUM_CLASSES - 1)
        if not config.saturation:
            return m[None].astype(np.float32), target
        candidates = saturation_candidates(m, frame.params)
        clipped = candidates & (frame.irradiance >= frame.params.max_wraps)
        inputs = np.stack([m, candidates]).astype(np.float32)
        return inputs, np.where(clipped, SATURATED, target)


def sample_batch(
    seed: int, step: int, config: PairConfig
) -> tuple[NDArray[np.float32], NDArray[np.int64]]:
    """Batch for ``step``: inputs as ``N x channels x H x W`` float32 and the target
    (``W``) as ``N x 1 x H x W`` int64."""
    rng = np.random.default_rng([seed, step])
    pairs = [sample_pair(rng, config) for _ in range(config.batch)]
    inputs = np.stack([p[0] for p in pairs])
    target = np.stack([p[1] for p in pairs])[:, None]
    return inputs, target
