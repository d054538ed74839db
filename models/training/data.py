"""On-the-fly training pairs ``(m, W)``, made with models.formation only.

A batch mixes random crops of the 14 training HDRIs (random 1x/2x downscale,
wrapping around the panorama seam) and seeded synthetic scenes; each crop gets
random flips and 90-degree rotations, a random exposure (overexposed fraction
0.05..0.35), a random ``max_wraps`` and optionally read noise. Grayscale (the HDRIs'
luminance), or with probability ``colour_fraction`` an HDRI crop in linear RGB,
exposed on its luminance as a colour frame is, of which one random channel makes the
pair: the nets decode colour frames channel by channel, and a channel is not a
luminance image (a blue sky can lie above saturation everywhere). With probability
``glow_fraction`` a synthetic scene also gets smooth bright lobes
(:func:`models.scenes.glows`): without them no training crop had a bright region
whose wrap rings could be counted, and the nets never answered W >= 3, even on a clean
glow that Itoh's method unwraps exactly. Everything is seeded by ``(seed, step)`` so a
resumed run sees the same data.
"""

from __future__ import annotations

import multiprocessing
import signal
from collections import deque
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from functools import cache
from multiprocessing.pool import AsyncResult
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

from models.errors import InvalidInputError
from models.formation import SensorParams, dequantize, from_unwrapped, simulate
from models.scenes import TRAIN_SCENES, load_hdri, load_hdri_gray, synthetic_scene
from models.training.networks import NUM_CLASSES

OVEREXPOSED_RANGE = (0.05, 0.35)


@dataclass(frozen=True)
class PairConfig:
    """What the sampler draws: encoding, crop size (px), batch size, noise range and the
    shares of synthetic scenes, of colour HDRI crops and of synthetic scenes with lobes."""

    encoding: str
    crop: int = 64
    batch: int = 8
    max_read_noise: float = 0.0
    synthetic_fraction: float = 0.5
    bits: int = 8
    colour_fraction: float = 0.0
    glow_fraction: float = 0.0


@cache
def _train_scenes(colour: bool = False) -> tuple[NDArray[np.float64], ...]:
    load = load_hdri if colour else load_hdri_gray
    return tuple(load(name) for name in TRAIN_SCENES)


def largest_crop() -> int:
    """The largest training crop (px): the smallest side of the smallest training
    panorama (a crop wraps around a panorama's seam, but not over its top or bottom)."""
    return min(min(scene.shape[:2]) for scene in _train_scenes())


def _hdri_crop(rng: np.random.Generator, size: int, colour: bool = False) -> NDArray[np.float64]:
    """A random ``size x size`` crop of a training HDRI (luminance, or linear RGB
    ``size x size x 3`` when ``colour``), at 1x or 2x downscale (1x only when the
    panorama, 256 px tall, has no room for 2x)."""
    scene = _train_scenes(colour)[int(rng.integers(len(TRAIN_SCENES)))]
    factor = int(rng.integers(1, min(2, scene.shape[0] // size) + 1))
    span = size * factor
    top = int(rng.integers(0, scene.shape[0] - span + 1))
    rows = np.roll(scene[top : top + span], -int(rng.integers(scene.shape[1])), axis=1)
    crop = rows[:, :span]
    return crop.reshape(size, factor, size, factor, *scene.shape[2:]).mean(axis=(1, 3))


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


def sample_pair(
    rng: np.random.Generator, config: PairConfig
) -> tuple[NDArray[np.float32], NDArray[np.int64]]:
    """One training pair: ``m`` (float32, crop x crop) and true ``W`` (int64)."""
    while True:
        if rng.uniform() < config.synthetic_fraction:
            seed = int(rng.integers(2**31))
            # No draw when glow_fraction is 0, so earlier recipes see the same data.
            lobes = bool(config.glow_fraction) and rng.uniform() < config.glow_fraction
            scene = synthetic_scene(seed, config.crop, lobes)
        else:
            # No draw when colour_fraction is 0, so grayscale recipes see the same data.
            colour = bool(config.colour_fraction) and rng.uniform() < config.colour_fraction
            scene = _hdri_crop(rng, config.crop, colour)
        noise = rng.uniform(0.0, config.max_read_noise) if rng.uniform() < 0.5 else 0.0
        params = SensorParams(
            encoding=config.encoding,  # type: ignore[arg-type]
            bits=config.bits,
            max_wraps=_max_wraps(rng, config.encoding),
            read_noise=noise,
            seed=int(rng.integers(2**31)),
        )
        augmented = _augment(rng, scene)
        overexposed = rng.uniform(*OVEREXPOSED_RANGE)
        try:
            frame = simulate(augmented, params, overexposed=overexposed)
        except InvalidInputError:
            continue
        codes, winding = frame.codes, frame.winding
        if codes.ndim == 3:
            channel = int(rng.integers(codes.shape[2]))
            codes, winding = codes[:, :, channel], winding[:, :, channel]
        winding = np.minimum(winding, NUM_CLASSES - 1)
        return dequantize(codes, config.bits).astype(np.float32), winding


def sample_batch(
    seed: int, step: int, config: PairConfig
) -> tuple[NDArray[np.float32], NDArray[np.int64]]:
    """Batch for ``step``: ``m`` as ``N x 1 x H x W`` float32 and ``W`` as ``N x 1 x H x W``."""
    rng = np.random.default_rng([seed, step])
    pairs = [sample_pair(rng, config) for _ in range(config.batch)]
    m = np.stack([p[0] for p in pairs])[:, None]
    winding = np.stack([p[1] for p in pairs])[:, None]
    return m, winding


class Batch(NamedTuple):
    """One optimizer step's data: ``m`` and ``W`` (``N x 1 x H x W``) and, for the
    ``ce-risk`` loss, the per-class errors of :func:`class_errors` (else None)."""

    m: NDArray[np.float32]
    winding: NDArray[np.int64]
    errors: NDArray[np.float32] | None


def training_batch(seed: int, step: int, config: PairConfig, with_errors: bool) -> Batch:
    """The batch of ``step`` (:func:`sample_batch`), with its class errors if asked."""
    m, winding = sample_batch(seed, step, config)
    errors = class_errors(m, winding, config.encoding) if with_errors else None
    return Batch(m, winding, errors)


def worker_signals() -> None:
    """A batch worker's signal handling, whatever the forked process inherited: SIGINT
    ignored, SIGTERM (how the pool ends its workers) ends it."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)


def batch_stream(
    seed: int, plan: Iterable[tuple[int, PairConfig]], with_errors: bool, workers: int = 0
) -> Iterator[Batch]:
    """The batches of ``plan`` (step, pair config) in order.

    With ``workers > 0`` they are made ahead in that many forked processes (as PyTorch's
    data loader does; they run numpy only, never the GPU), at most two per worker in
    flight (a GPU step outruns one CPU core's batch). Every batch depends only on
    ``(seed, step, config)``, so the stream is the same for any ``workers``. The workers
    leave SIGINT (a Ctrl-C reaches the whole process group) to the training process,
    which ends them when it stops.
    """
    if workers <= 0:
        for step, config in plan:
            yield training_batch(seed, step, config, with_errors)
        return
    with multiprocessing.get_context("fork").Pool(workers, worker_signals) as pool:
        pending: deque[AsyncResult[Batch]] = deque()
        for step, config in plan:
            pending.append(pool.apply_async(training_batch, (seed, step, config, with_errors)))
            if len(pending) >= 2 * workers:
                yield pending.popleft().get()
        while pending:
            yield pending.popleft().get()


def class_errors(
    m: NDArray[np.float32], winding: NDArray[np.int64], encoding: str
) -> NDArray[np.float32]:
    """Squared irradiance error of answering each W class, relative to each crop's peak.

    ``((x(k + m) - x(W + m)) / peak)^2`` for every class ``k`` (``N x NUM_CLASSES x H x W``
    from ``N x 1 x H x W`` inputs), with ``x`` in wrap units (the training alpha, 2) and
    ``peak`` the crop's largest true ``x``, as the PSNR metric scales it. On mantissa
    frames one wrap too many at ``x = 8`` costs 64, at ``x = 0.5`` about 0.8: the few
    bright pixels decide the PSNR, and a far-too-high W on a dark pixel ruins it.
    """
    params = SensorParams(encoding=encoding)  # type: ignore[arg-type]
    classes = np.arange(NUM_CLASSES, dtype=np.float64).reshape(1, -1, 1, 1)
    truth = from_unwrapped(winding.astype(np.float64) + m, params)
    answers = from_unwrapped(classes + m, params)
    peak = np.maximum(truth.max(axis=(1, 2, 3), keepdims=True), 1e-3)
    return (((answers - truth) / peak) ** 2).astype(np.float32)
