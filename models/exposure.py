"""Exposure of a scene on a wrapping sensor: the gain that overexposes a chosen fraction
of pixels (:func:`exposure_gain`, on Rec.709 :func:`luminance`), and the check that a
simulated frame is not all code 0 (:func:`check_not_black`).

Values are scene-referred irradiance (any positive scale) and wrap units ``x = scene *
gain`` (``x = 1``: the first wrap), as in :mod:`models.formation`.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from models.errors import InvalidInputError

if TYPE_CHECKING:
    from models.formation import SensorFrame

REC709_WEIGHTS = np.array([0.2126, 0.7152, 0.0722])


def luminance(rgb: NDArray[np.floating]) -> NDArray[np.float64]:
    """Rec.709 luminance of an ``H x W x 3`` image; a 2-D image is returned as is."""
    arr = np.asarray(rgb, dtype=np.float64)
    if arr.ndim == 2:
        return arr
    if arr.ndim != 3 or arr.shape[2] != 3:
        raise InvalidInputError(f"expected H x W or H x W x 3, got shape {arr.shape}")
    return arr @ REC709_WEIGHTS


def check_overexposed(overexposed: float) -> None:
    """Refuse an ``overexposed`` fraction outside the open interval (0, 1), saying why
    and what to give instead."""
    if 0.0 < overexposed < 1.0:
        return
    if np.isnan(overexposed):
        problem = "got NaN (not a number)"
    elif overexposed == 1.0:
        problem = (
            "got 1: every pixel, the darkest included, at x >= 1 leaves no pixel below "
            "its first wrap"
        )
    elif overexposed > 1.0:
        meant = f" (for {overexposed:g}%, give {overexposed / 100:g})" if overexposed <= 100 else ""
        problem = f"got {overexposed:g}, more than every pixel{meant}"
    else:
        problem = f"got {overexposed:g}, which overexposes no pixel"
    raise InvalidInputError(
        f"overexposed is the fraction of pixels the gain brings to x >= 1, strictly between 0 "
        f"and 1; {problem}: give a fraction such as 0.2 (or 0.99 for nearly all), or the gain "
        "instead"
    )


def _round_down(value: float, digits: int = 3) -> float:
    """``value`` (> 0) rounded down to ``digits`` significant digits."""
    scale = 10.0 ** (digits - 1 - int(np.floor(np.log10(value))))
    return float(np.floor(value * scale) / scale)


def _black_share_error(lum: NDArray[np.float64], overexposed: float) -> InvalidInputError:
    """The error for an ``overexposed`` whose exposure level (a luminance quantile of
    ``lum``) is 0: more pixels are black than ``1 - overexposed``, and no gain brings
    them to x >= 1."""
    black = int(np.count_nonzero(lum <= 0.0))
    if black == lum.size:
        return InvalidInputError(
            "the scene is black (every pixel has zero luminance): no gain exposes it; check "
            "that the image holds the scene (negative values clipped to 0 count as black)"
        )
    share = black / lum.size
    return InvalidInputError(
        f"overexposed {overexposed:g} asks for all but the darkest "
        f"{100 * (1.0 - overexposed):.3g}% of pixels at x >= 1, but {black} of {lum.size} "
        f"pixels ({100 * share:.3g}%) have zero luminance (black, or negative values clipped "
        "to 0) and no gain raises them: give "
        f"overexposed at most {_round_down(1.0 - share)} (the share of pixels that are not "
        "black), or the gain instead"
    )


def _no_dark_pixel_error(
    lum: NDArray[np.float64], level: float, overexposed: float
) -> InvalidInputError:
    """The error for an ``overexposed`` whose exposure level is the darkest luminance of
    ``lum`` (> 0): the pixels that share it reach x >= 1 with all the others, and no pixel
    is left below the first wrap, where a decoder anchors the winding numbers (W = 0)."""
    tied = int(np.count_nonzero(lum <= level))
    if tied == lum.size:
        return InvalidInputError(
            f"every pixel of the scene has the luminance {level:.4g}: any overexposed "
            "fraction brings them all to x >= 1 together, leaving no pixel below the first "
            "wrap, and no decoder can tell their winding number; give the gain instead "
            f"(below {1.0 / level:.4g} keeps them under the first wrap)"
        )
    return InvalidInputError(
        f"overexposed {overexposed:g} sets the exposure at the scene's darkest luminance, "
        f"{level:.4g}, which {tied} of {lum.size} pixels ({100 * tied / lum.size:.3g}%) "
        "share: every pixel reaches x >= 1, leaving none below the first wrap, and no decoder "
        f"can tell their winding numbers; give overexposed at most "
        f"{_round_down(1.0 - tied / lum.size)} (the share of pixels brighter than them), or "
        "the gain instead"
    )


def exposure_gain(scene: NDArray[np.floating], overexposed: float) -> float:
    """Gain such that a fraction ``overexposed`` (strictly between 0 and 1) of pixels
    reach ``x >= 1``.

    ``gain = 1 / quantile(luminance, 1 - overexposed)``; an exposure level of 0 (more
    pixels black than ``1 - overexposed``), one at the darkest luminance (more pixels
    share it than ``1 - overexposed``: every pixel would reach x >= 1) or one whose
    inverse overflows is refused.
    """
    check_overexposed(overexposed)
    lum = luminance(scene)
    level = float(np.quantile(lum, 1.0 - overexposed))
    if level <= 0.0:
        raise _black_share_error(lum, overexposed)
    if level <= float(lum.min()):
        raise _no_dark_pixel_error(lum, level, overexposed)
    with np.errstate(over="ignore"):
        gain = 1.0 / level
    if not np.isfinite(gain):
        raise InvalidInputError(
            f"overexposed {overexposed:g} sets the exposure at a luminance of {level:.3g}, "
            "so small that its gain (1 / luminance) overflows float64: scale the scene up, "
            "or give the gain instead"
        )
    # 1 / level can round down (49 * (1 / 49) < 1): one ulp up keeps the quantile pixel at x >= 1.
    return gain if level * gain >= 1.0 else float(np.nextafter(gain, np.inf))


def check_not_black(frame: SensorFrame) -> None:
    """Refuse a simulated frame whose every code is 0 although the scene it saw is not
    black: every pixel stores a fraction ``m`` under one code step (``2^-bits`` wraps),
    below the first wrap or just past a later one (the pixels an ``overexposed`` fraction
    puts exactly at ``x = 1``, when they share one luminance, store ``m = 0``), so the
    frame holds nothing of the scene; the error gives the smallest gain that lifts a
    pixel to one step (:func:`_least_lifting_gain`)."""
    brightest = float(frame.irradiance.max())
    if brightest <= 0 or frame.codes.any():
        return
    bits = frame.params.bits
    step = 2.0**-bits
    gain = frame.params.gain if frame.params.gain is not None else 1.0
    top = frame.params.max_wraps
    if top is not None and bool(np.all(frame.irradiance[frame.irradiance > 0] >= top)):
        raise InvalidInputError(_all_clipped_message(frame, gain, top))
    least = _least_lifting_gain(frame, gain, step)
    raise_to = f" to at least {least:.4g}" if np.isfinite(least) else ""
    wrapped = int(np.count_nonzero(frame.winding))
    where = (
        f"the brightest is x = {brightest:.4g} wrap units, under one {bits}-bit code step "
        f"of {step:.4g}"
        if not wrapped
        else f"{wrapped} pixels lie just past a wrap, x = {brightest:.4g} at the brightest, "
        f"and store a fraction under one {bits}-bit code step of {step:.4g}, as the rest do"
    )
    raise InvalidInputError(
        f"every pixel quantises to code 0 ({where}, at gain {gain:.4g}): raise the gain"
        f"{raise_to}, or let overexposed set it (e.g. 0.01; --gain and --overexposed on the "
        "command line)"
    )


def _all_clipped_message(frame: SensorFrame, gain: float, top: float) -> str:
    """Why a frame of every code 0 whose lit pixels all sit at the clip ``top``
    (``max_wraps``, wrap units) holds nothing, and what to do: ``u(top)`` lies under one
    code step past a whole number of wraps, which stores code 0, and no gain lifts a
    clipped pixel (a higher one clips it too)."""
    lit = int(np.count_nonzero(frame.irradiance))
    return (
        f"every pixel quantises to code 0: all {lit} lit pixels are clipped at max_wraps "
        f"= {top:g} wrap units (at gain {gain:.4g}), stored as "
        f"{int(frame.winding.max())} whole wraps, code 0 like black; lower the gain, or let "
        "overexposed set it (e.g. 0.01; --gain and --overexposed on the command line), or "
        "clip at another max_wraps"
    )


def _least_lifting_gain(frame: SensorFrame, gain: float, step: float) -> float:
    """The smallest gain at which a pixel of ``frame`` (taken at ``gain``) that is lit
    and not clipped at ``max_wraps`` stores one code step ``step`` past its wrap
    ``W``: ``u = W + step``, ``x = u`` (``alpha^(u - 1)`` for mantissa from ``u = 1``);
    inf when no pixel can be lifted."""
    params = frame.params
    x = frame.irradiance
    top = np.inf if params.max_wraps is None else params.max_wraps
    liftable = (x > 0) & (x < top)
    target = frame.winding[liftable] + step
    if params.encoding == "mantissa":
        with np.errstate(over="ignore"):
            target = np.where(target >= 1.0, params.alpha ** (target - 1.0), target)
    with np.errstate(over="ignore"):
        factors = gain * (target / x[liftable])
    return float(factors.min(initial=np.inf))
