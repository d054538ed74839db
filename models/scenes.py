"""HDR scenes for training and evaluation: the shipped HDRIs, a seeded synthetic
generator, the fixed train/validation split and the "val-256" evaluation protocol.

Scenes are scene-referred linear irradiance (any positive scale); frames are made
from them only through :func:`models.formation.simulate`.

val-256 (the benchmark's fixed protocol): :data:`VAL256_CROPS_PER_SCENE` seeded
256 x 256 grayscale crops of each validation scene (``forest``, ``lobby``,
``venice``), exposed so that 20% of pixels exceed one wrap (``overexposed=0.2``),
``max_wraps=16``, 8 bits, ``alpha=2``, read noise 0 or as asked.
"""

from __future__ import annotations

from functools import cache
from pathlib import Path
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

from models.errors import InvalidInputError, McamError
from models.exposure import luminance
from models.formation import SensorFrame, SensorParams, simulate
from models.hdr_io import read_hdr

HDRI_DIR = Path(__file__).resolve().parent / "data" / "hdri"
VAL_SCENES: tuple[str, ...] = ("forest", "lobby", "venice")
TRAIN_SCENES: tuple[str, ...] = (
    "apartment", "bridge", "city", "dawn", "esplanade", "hall", "lab",
    "night", "park", "sky", "studio", "sunset", "warehouse", "workshop",
)  # fmt: skip
SCENE_NAMES: tuple[str, ...] = tuple(sorted(TRAIN_SCENES + VAL_SCENES))

VAL256_SIZE = 256
VAL256_CROPS_PER_SCENE = 8
VAL256_SEED = 256
VAL256_OVEREXPOSED = 0.2
VAL256_MAX_WRAPS = 16.0
VAL256_BITS = 8


class ValFrame(NamedTuple):
    """One val-256 frame: codes (DN), true W, exact x (wrap units), params (with gain)."""

    codes: NDArray[np.unsignedinteger]
    winding: NDArray[np.int64]
    x: NDArray[np.float64]
    params: SensorParams


#: What to do about a shipped scene that is missing or cannot be read.
RESTORE_SCENES = (
    "the scenes ship in models/data/hdri: restore them (git checkout -- models/data/hdri), "
    "or recreate them as its README.md says"
)


@cache
def _load_hdri(name: str) -> tuple[NDArray[np.float64], int]:
    """Scene ``name`` (linear RGB, negatives set to 0) and how many negatives it had; a
    missing or unreadable file says so and how to restore the shipped scenes (it was
    told to create the folder, or to convert the file to OpenEXR)."""
    if name not in SCENE_NAMES:
        raise InvalidInputError(f"unknown scene {name!r}; choose one of: {', '.join(SCENE_NAMES)}")
    path = HDRI_DIR / f"{name}.exr"
    try:
        image = read_hdr(path, clip_negative=True)
    except FileNotFoundError:
        raise FileNotFoundError(f"scene {name!r} is missing ({path}); {RESTORE_SCENES}") from None
    except McamError as exc:
        reason = exc.message.split("; ")[0]  # its advice (convert it) does not apply here
        raise InvalidInputError(
            f"scene {name!r} cannot be read ({reason}); {RESTORE_SCENES}"
        ) from None
    image.pixels.setflags(write=False)
    return image.pixels, image.negatives_clipped


def load_hdri(name: str) -> NDArray[np.float64]:
    """Scene ``name`` as linear RGB ``H x W x 3`` float64, negatives (DWAB) set to 0."""
    return _load_hdri(name)[0]


def clipped_negatives(name: str) -> int:
    """How many negative channel values the lossy EXR of scene ``name`` had (set to 0)."""
    return _load_hdri(name)[1]


def load_hdri_gray(name: str) -> NDArray[np.float64]:
    """Rec.709 luminance of scene ``name``, ``H x W`` float64."""
    return luminance(load_hdri(name))


def val256_crop_offsets(width: int, count: int, seed: int) -> list[int]:
    """Seeded, distinct horizontal crop offsets (columns) on a 360-degree panorama."""
    rng = np.random.default_rng(seed)
    return sorted(int(o) for o in rng.choice(width, size=count, replace=False))


def panorama_crops(
    names: tuple[str, ...], per_scene: int, seed: int, colour: bool = False
) -> list[tuple[str, NDArray[np.float64]]]:
    """``per_scene`` seeded 256 x 256 crops of each scene of ``names`` as ``(label,
    crop)``, in a fixed order: luminance (H x W), or linear RGB (H x W x 3) when
    ``colour``.

    The panoramas are 256 pixels tall (the middle rows are taken otherwise); each crop
    is a 256-column window at a seeded offset (:func:`val256_crop_offsets`, seed
    ``seed`` + the scene's index), wrapping around the 360-degree seam.
    """
    crops = []
    for index, name in enumerate(names):
        scene = load_hdri(name) if colour else load_hdri_gray(name)
        top = (scene.shape[0] - VAL256_SIZE) // 2
        rows = scene[top : top + VAL256_SIZE]
        for offset in val256_crop_offsets(scene.shape[1], per_scene, seed + index):
            crop = np.roll(rows, -offset, axis=1)[:, :VAL256_SIZE]
            crops.append((f"{name}@{offset}", np.ascontiguousarray(crop)))
    return crops


def val256_scenes(colour: bool = False) -> list[tuple[str, NDArray[np.float64]]]:
    """The val-256 crops as ``(label, luminance 256 x 256)`` (or linear RGB 256 x 256 x 3
    when ``colour``), in a fixed order (:func:`panorama_crops`)."""
    return panorama_crops(VAL_SCENES, VAL256_CROPS_PER_SCENE, VAL256_SEED, colour)


def exposed_frames(
    crops: list[tuple[str, NDArray[np.float64]]],
    encoding: str,
    read_noise: float = 0.0,
    seed: int = VAL256_SEED,
) -> list[ValFrame]:
    """Each crop as a frame at the val-256 settings for ``encoding``: overexposed 0.2,
    max_wraps 16, 8 bits, alpha 2; read noise (wrap units) seeded per crop (``seed`` +
    its index)."""
    frames = []
    for index, (_, crop) in enumerate(crops):
        params = SensorParams.parse(
            {
                "encoding": encoding,
                "bits": VAL256_BITS,
                "max_wraps": VAL256_MAX_WRAPS,
                "read_noise": read_noise,
                "seed": seed + index,
            }
        )
        frame = simulate(crop, params, overexposed=VAL256_OVEREXPOSED)
        frames.append(ValFrame(frame.codes, frame.winding, frame.irradiance, frame.params))
    return frames


def val256_frames(encoding: str, read_noise: float = 0.0, colour: bool = False) -> list[ValFrame]:
    """The fixed val-256 evaluation set for ``encoding`` (``modulo`` or ``mantissa``).

    24 frames (3 scenes x 8 crops), 256 x 256 grayscale (or RGB when ``colour``: the
    same crops, exposed on their luminance), overexposed 0.2, max_wraps 16, 8 bits,
    alpha 2; read noise (wrap units) seeded per crop.
    """
    return exposed_frames(val256_scenes(colour), encoding, read_noise)


def _disk_mask(size: int, cy: float, cx: float, radius: float) -> tuple[slice, slice, NDArray]:
    """Bounding-box slices and boolean mask of a disk on a ``size x size`` canvas."""
    y0, y1 = max(int(cy - radius), 0), min(int(cy + radius) + 1, size)
    x0, x1 = max(int(cx - radius), 0), min(int(cx + radius) + 1, size)
    yy, xx = np.ogrid[y0:y1, x0:x1]
    return slice(y0, y1), slice(x0, x1), (yy - cy) ** 2 + (xx - cx) ** 2 <= radius**2


def _texture(rng: np.random.Generator, shape: tuple[int, int]) -> NDArray[np.float64]:
    """A multiplicative texture around 1: a random sinusoidal grating plus fine noise."""
    yy, xx = np.mgrid[0 : shape[0], 0 : shape[1]]
    freq, angle = rng.uniform(0.05, 0.6), rng.uniform(0, np.pi)
    grating = np.sin(freq * (np.cos(angle) * xx + np.sin(angle) * yy) + rng.uniform(0, 6.3))
    noise = rng.standard_normal(shape)
    return np.exp(rng.uniform(0, 0.5) * grating + rng.uniform(0, 0.15) * noise)


def glows(rng: np.random.Generator, size: int, median: float) -> NDArray[np.float64]:
    """One to four smooth bright lobes to add to a ``size x size`` scene whose median
    radiance is ``median``: a light's glare or a lamp's fall-off on a wall (power law
    ``(1 + d^2 / s^2)^-1``) or a specular highlight (Gaussian), of width ``s`` 2 px to a
    third of the frame and peak 10 to 10^4 x the median. Unlike the dead leaves' sharp
    disks, a lobe of peak ``P`` crosses every wrap up to ``P`` within a few pixels of
    the last: a bright region whose W the codes decide, ring by ring."""
    yy, xx = np.mgrid[0:size, 0:size].astype(np.float64)
    out = np.zeros((size, size))
    for _ in range(int(rng.integers(1, 5))):
        cy, cx = rng.uniform(-0.25 * size, 1.25 * size, 2)
        width = 10 ** rng.uniform(np.log10(2.0), np.log10(size / 3))
        squared = ((yy - cy) ** 2 + (xx - cx) ** 2) / width**2
        shape = np.exp(-0.5 * squared) if rng.uniform() < 0.5 else 1.0 / (1.0 + squared)
        out += median * 10 ** rng.uniform(1.0, 4.0) * shape
    return out


def add_glows(scene: NDArray[np.float64], rng: np.random.Generator) -> NDArray[np.float64]:
    """``scene`` (square, luminance) with :func:`glows` added, scaled to its median."""
    return scene + glows(rng, scene.shape[0], float(np.median(scene)))


def synthetic_scene(seed: int, size: int = 128, lobes: bool = False) -> NDArray[np.float64]:
    """A seeded synthetic HDR luminance scene, ``size x size`` float64 (> 0).

    Dead leaves (disks with power-law radii, occluding each other) with
    heavy-tailed radiances (log-normal, or Pareto for a fraction), textured
    surfaces, a few small very bright sources, a smooth gradient and vignetting;
    with ``lobes``, also smooth bright lobes (:func:`glows`, drawn from their own
    seeded stream: the rest of the scene is the same either way).
    """
    rng = np.random.default_rng(seed)
    scene = np.full((size, size), rng.lognormal(0.0, 1.0))
    r_min, r_max = 1.5, size / 2
    for _ in range(int(rng.integers(30, 120))):
        radius = (r_min**-2 - rng.uniform() * (r_min**-2 - r_max**-2)) ** -0.5
        cy, cx = rng.uniform(-radius, size + radius, 2)
        ys, xs, mask = _disk_mask(size, cy, cx, radius)
        if not mask.any():
            continue
        level = rng.pareto(1.5) + 1.0 if rng.uniform() < 0.2 else rng.lognormal(0.0, 1.5)
        patch = level * (_texture(rng, mask.shape) if rng.uniform() < 0.5 else 1.0)
        scene[ys, xs] = np.where(mask, patch, scene[ys, xs])
    for _ in range(int(rng.integers(0, 5))):
        cy, cx = rng.uniform(0, size, 2)
        ys, xs, mask = _disk_mask(size, cy, cx, rng.uniform(0.5, 3.0))
        bright = np.median(scene) * 10 ** rng.uniform(2, 5)
        scene[ys, xs] = np.where(mask, bright, scene[ys, xs])
    if lobes:
        scene = add_glows(scene, np.random.default_rng([seed, 1]))
    yy, xx = np.mgrid[0:size, 0:size] / size - 0.5
    angle = rng.uniform(0, 2 * np.pi)
    gradient = np.exp(rng.uniform(0, 3) * (np.cos(angle) * xx + np.sin(angle) * yy))
    vignette = np.cos(np.clip(rng.uniform(0, 1.2) * np.hypot(xx, yy), 0, 1.5)) ** 4
    return scene * gradient * vignette + 1e-6


def synthetic_val256_frame(
    encoding: str, size: int = VAL256_SIZE, seed: int = 0, colour: bool = False
) -> SensorFrame:
    """Seeded synthetic scene ``seed`` (``size`` x ``size``) exposed and encoded as
    val-256 frames are (overexposed 0.2, max_wraps 16, 8 bits, no noise): a stand-in
    frame for timing and warming decoders that uses no validation scene. ``colour``:
    linear RGB, the scene tinted by :func:`synthetic_tint`."""
    params = SensorParams(
        encoding=encoding,  # type: ignore[arg-type]
        bits=VAL256_BITS,
        max_wraps=VAL256_MAX_WRAPS,
    )
    scene = synthetic_scene(seed, size)
    if colour:
        scene = scene[:, :, None] * synthetic_tint(seed, size)
    return simulate(scene, params, overexposed=VAL256_OVEREXPOSED)


def synthetic_tint(seed: int, size: int) -> NDArray[np.float64]:
    """Seeded smooth per-channel gains (``size`` x ``size`` x 3, around 1): red and blue
    tilted from green by smooth log-chroma fields of up to 0.6 (natural log), as
    natural scenes' chroma varies slowly."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:size, 0:size] / size
    fields = [
        rng.uniform(-0.4, 0.4) * np.sin(rng.uniform(1, 4) * xx + rng.uniform(0, 6.3))
        + rng.uniform(-0.2, 0.2) * np.cos(rng.uniform(1, 4) * yy)
        for _ in range(2)
    ]
    return np.exp(np.stack([fields[0], np.zeros((size, size)), fields[1]], axis=2))
