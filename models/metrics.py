"""Quality metrics of a reconstruction against a reference (``mcam evaluate``, cards, benches).

Images are linear HDR (wrap units or scene-referred, the same scale for both),
``H x W`` or ``H x W x 3``. All metrics reject NaN, inf, negative values and
shape mismatches with :class:`InvalidInputError`.

- ``winding_accuracy``: fraction of pixels whose winding number is exactly right.
- ``psnr``: on linear values, peak = reference max. Identical images give
  ``float('inf')`` (callers writing JSON must map it, e.g. to ``null``).
- ``pu21_psnr``: both images scaled so the reference max is 4000 cd/m^2, PU21
  encoded per channel (see :mod:`models.pu21`), peak = PU21(10000 cd/m^2) = 595.4.
  The PU21 reference's ``pu21_metric`` takes a peak of 256 instead: its figures are
  20 log10(595.4 / 256) = 7.33 dB below these on the same images.
- ``capped_psnr``: a PSNR averaged over frames, capped at ``PSNR_CAP`` dB (an exact
  frame's inf counts as the cap, so one bad frame among exact ones still shows);
  ``mean_capped_psnr`` averages them.
- ``ssim`` / ``ms_ssim``: on Reinhard-tonemapped luminance (key 0.18 of the
  reference's log-average luminance, the same scale applied to both images).
  SSIM uses an 11 x 11 Gaussian window (sigma 1.5), K1 = 0.01, K2 = 0.03, data
  range 1 (Wang et al. 2004). MS-SSIM uses the 5-scale weights of Wang et al.
  (2003) with 2 x 2 average downsampling; an image too small for 5 scales (the
  coarsest must still be >= 11 px, i.e. min side >= 176) uses as many scales
  as fit with the first weights renormalized to sum to 1 (one scale is SSIM). Negative
  contrast-structure terms are clamped to 0 before the fractional powers.
- ``hdr_flip``: mean HDR-FLIP error (NVIDIA), only when the optional
  ``flip-evaluator`` package is installed, else ``None``.
"""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.ndimage import correlate1d

from models.errors import InvalidInputError
from models.exposure import luminance
from models.formation import validate_irradiance
from models.pu21 import PU21_PEAK, pu21_encode

#: Absolute luminance (cd/m^2) the reference maximum is mapped to for PU21.
PU21_DISPLAY_PEAK = 4000.0
#: Reinhard key: the log-average luminance of the reference maps to this.
REINHARD_KEY = 0.18
#: Offset in the log-average, relative to the reference's maximum luminance.
LOG_AVERAGE_DELTA = 1e-6
#: Side of the SSIM Gaussian window and its sigma, in pixels.
SSIM_WINDOW = 11
SSIM_SIGMA = 1.5
SSIM_K1, SSIM_K2 = 0.01, 0.03
#: MS-SSIM weights per scale, finest first (Wang, Simoncelli & Bovik 2003).
MS_SSIM_WEIGHTS = (0.0448, 0.2856, 0.3001, 0.2363, 0.1333)


def validate_pair(
    estimate: ArrayLike, reference: ArrayLike
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Both images as float64 after checking they are finite, non-negative, same shape."""
    x, _ = validate_irradiance(np.asarray(estimate))
    ref, _ = validate_irradiance(np.asarray(reference))
    if x.ndim == 3 and x.shape[2] == 1:
        x = x[:, :, 0]
    if ref.ndim == 3 and ref.shape[2] == 1:
        ref = ref[:, :, 0]
    if x.shape != ref.shape:
        raise InvalidInputError(
            f"the estimate's shape {x.shape} does not match the reference's {ref.shape}; "
            "compare images of the same size and channel count"
        )
    return x, ref


def _reference_peak(reference: NDArray[np.float64]) -> float:
    peak = float(reference.max())
    if peak <= 0.0:
        raise InvalidInputError("the reference image is all zero; no peak to measure against")
    return peak


def _psnr(a: NDArray[np.float64], b: NDArray[np.float64], peak: float) -> float:
    mse = float(np.mean((a - b) ** 2))
    if mse == 0.0:
        return float("inf")
    return float(20.0 * np.log10(peak) - 10.0 * np.log10(mse))


def winding_accuracy(winding: ArrayLike, winding_ref: ArrayLike) -> float:
    """Fraction of pixels (0..1) whose winding number equals the reference's."""
    w, w_ref = np.asarray(winding), np.asarray(winding_ref)
    if w.shape != w_ref.shape:
        raise InvalidInputError(
            f"winding map shape {w.shape} does not match the reference {w_ref.shape}"
        )
    if w.size == 0:
        raise InvalidInputError("the winding maps are empty")
    if w.dtype.kind not in "iu" or w_ref.dtype.kind not in "iu":
        raise InvalidInputError(
            f"winding numbers must be integers, got {w.dtype} and {w_ref.dtype}"
        )
    return float(np.mean(w == w_ref))


def psnr(estimate: ArrayLike, reference: ArrayLike) -> float:
    """PSNR in dB of linear HDR values, peak = reference max; ``inf`` when identical."""
    x, ref = validate_pair(estimate, reference)
    peak = _reference_peak(ref)
    return _psnr(x / peak, ref / peak, 1.0)


def pu21_psnr(estimate: ArrayLike, reference: ArrayLike) -> float:
    """PSNR in dB of PU21-encoded absolute luminance (reference max -> 4000 cd/m^2).

    Each channel is encoded as luminance, as the PU21 reference's colour PSNR
    does; the peak is PU21(10000 cd/m^2) = 595.4, where the reference's
    ``pu21_metric`` takes 256 (its figures are 7.33 dB lower).
    """
    x, ref = validate_pair(estimate, reference)
    scale = PU21_DISPLAY_PEAK / _reference_peak(ref)
    return _psnr(pu21_encode(x * scale), pu21_encode(ref * scale), PU21_PEAK)


#: Per-frame PSNR (dB) counted for a frame reconstructed exactly (its PSNR is inf).
PSNR_CAP = 100.0


def capped_psnr(value: float) -> float:
    """A per-frame PSNR (dB) to average: at most :data:`PSNR_CAP` (an exact frame's inf
    counts as the cap). NaN or -inf is a bug upstream and is refused."""
    if np.isnan(value) or value == -np.inf:
        raise InvalidInputError(f"a PSNR of {value} cannot be averaged: it is not a number")
    return min(float(value), PSNR_CAP)


def mean_capped_psnr(values: Iterable[float]) -> float:
    """Mean of per-frame PSNRs (dB), each at most :data:`PSNR_CAP` (:func:`capped_psnr`);
    NaN for no frame."""
    capped = [capped_psnr(value) for value in values]
    return float(np.mean(capped)) if capped else float("nan")


def reinhard(image: ArrayLike, reference: ArrayLike) -> NDArray[np.float64]:
    """Reinhard global tonemap of the luminance of ``image``, keyed on ``reference``.

    ``L = 0.18 * Y / Ybar_ref`` and ``L / (1 + L)`` in [0, 1], where ``Ybar_ref`` is
    the log-average of the reference's luminance (offset by 1e-6 of its maximum). A
    pixel whose ``L`` is past float64 (``Y`` over about 1e309 times ``Ybar_ref``: a
    frame of a clip keyed on a far darker one) maps to 1, the limit of ``L / (1 + L)``:
    inf / inf made it NaN.
    """
    x, ref = validate_pair(image, reference)
    ref_luminance = luminance(ref)
    delta = LOG_AVERAGE_DELTA * _reference_peak(ref_luminance)
    log_average = float(np.exp(np.mean(np.log(delta + ref_luminance))))
    with np.errstate(over="ignore"):
        scaled = luminance(x) * (REINHARD_KEY / log_average)
    tone = np.ones_like(scaled)
    return np.divide(scaled, 1.0 + scaled, out=tone, where=np.isfinite(scaled))


def _gaussian_window() -> NDArray[np.float64]:
    taps = np.arange(SSIM_WINDOW) - SSIM_WINDOW // 2
    window = np.exp(-(taps**2) / (2.0 * SSIM_SIGMA**2))
    return window / window.sum()


def _local_mean(image: NDArray[np.float64]) -> NDArray[np.float64]:
    """Gaussian-weighted local means, only where the window fits (the 'valid' part)."""
    window = _gaussian_window()
    filtered = correlate1d(correlate1d(image, window, axis=0), window, axis=1)
    edge = SSIM_WINDOW // 2
    return filtered[edge:-edge, edge:-edge]


def _ssim_maps(
    a: NDArray[np.float64], b: NDArray[np.float64], data_range: float
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """SSIM luminance and contrast-structure maps of two images."""
    if min(a.shape) < SSIM_WINDOW:
        raise InvalidInputError(
            f"SSIM needs images of at least {SSIM_WINDOW} x {SSIM_WINDOW} pixels, got {a.shape}"
        )
    c1 = (SSIM_K1 * data_range) ** 2
    c2 = (SSIM_K2 * data_range) ** 2
    mu_a, mu_b = _local_mean(a), _local_mean(b)
    var_a = _local_mean(a * a) - mu_a**2
    var_b = _local_mean(b * b) - mu_b**2
    cov = _local_mean(a * b) - mu_a * mu_b
    lum = (2.0 * mu_a * mu_b + c1) / (mu_a**2 + mu_b**2 + c1)
    cs = (2.0 * cov + c2) / (var_a + var_b + c2)
    return lum, cs


def _check_planes(a: ArrayLike, b: ArrayLike) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    a64, b64 = np.asarray(a, np.float64), np.asarray(b, np.float64)
    if a64.shape != b64.shape or a64.ndim != 2:
        raise InvalidInputError(
            f"SSIM compares two single-channel images of one shape, got {a64.shape}, {b64.shape}"
        )
    for name, plane in (("first", a64), ("second", b64)):
        bad = int(np.count_nonzero(~np.isfinite(plane) | (plane < 0)))
        if bad:
            raise InvalidInputError(
                f"SSIM takes finite values >= 0: the {name} image has {bad} that are not"
            )
    return a64, b64


def ssim_ldr(a: ArrayLike, b: ArrayLike, data_range: float = 1.0) -> float:
    """Mean SSIM of two single-channel display-referred images (values in [0, data_range])."""
    a64, b64 = _check_planes(a, b)
    lum, cs = _ssim_maps(a64, b64, data_range)
    return float(np.mean(lum * cs))


def ms_ssim_scales(shape: tuple[int, ...]) -> int:
    """How many MS-SSIM scales (1..5) fit: the coarsest must be >= the SSIM window."""
    scales = 1
    side = min(shape[:2])
    while scales < len(MS_SSIM_WEIGHTS) and side // 2 >= SSIM_WINDOW:
        side //= 2
        scales += 1
    return scales


def _downsample(image: NDArray[np.float64]) -> NDArray[np.float64]:
    """2 x 2 block average (an odd last row or column is dropped)."""
    rows, cols = image.shape[0] // 2 * 2, image.shape[1] // 2 * 2
    cropped = image[:rows, :cols]
    return 0.25 * (
        cropped[0::2, 0::2] + cropped[1::2, 0::2] + cropped[0::2, 1::2] + cropped[1::2, 1::2]
    )


def ms_ssim_ldr(a: ArrayLike, b: ArrayLike, data_range: float = 1.0) -> float:
    """MS-SSIM of two single-channel display-referred images (see the module notes)."""
    a64, b64 = _check_planes(a, b)
    scales = ms_ssim_scales(a64.shape)
    weights = np.array(MS_SSIM_WEIGHTS[:scales])
    if scales < len(MS_SSIM_WEIGHTS):
        weights /= weights.sum()
    terms = []
    for scale in range(scales):
        lum, cs = _ssim_maps(a64, b64, data_range)
        if scale < scales - 1:
            terms.append(float(np.mean(cs)))
            a64, b64 = _downsample(a64), _downsample(b64)
        else:
            terms.append(float(np.mean(lum * cs)))
    return float(np.prod(np.maximum(terms, 0.0) ** weights))


def ssim(estimate: ArrayLike, reference: ArrayLike) -> float:
    """SSIM of the Reinhard-tonemapped luminances (see :func:`reinhard`)."""
    return ssim_ldr(reinhard(estimate, reference), reinhard(reference, reference))


def ms_ssim(estimate: ArrayLike, reference: ArrayLike) -> float:
    """MS-SSIM of the Reinhard-tonemapped luminances (see :func:`reinhard`)."""
    return ms_ssim_ldr(reinhard(estimate, reference), reinhard(reference, reference))


def flip_inputs(
    estimate: NDArray[np.float64], reference: NDArray[np.float64]
) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
    """Both images as float32 RGB, divided by the reference's peak (so it is 1).

    HDR-FLIP picks its exposures from the reference's median and maximum luminance, so
    a common scale does not change its error; but it computes them in float32 with a
    floor near 1e-7 and ends the process (a C++ ``exit``) when the range comes out
    empty, as it does for a reference of ~1e-8. At peak 1 the range is always usable.
    Estimate values beyond float32 after the division are clipped to its largest."""
    peak = _reference_peak(reference)
    limit = float(np.finfo(np.float32).max)
    x = np.minimum(estimate / peak, limit).astype(np.float32)
    ref = (reference / peak).astype(np.float32)
    if x.ndim == 2:
        x, ref = np.repeat(x[:, :, None], 3, axis=2), np.repeat(ref[:, :, None], 3, axis=2)
    return x, ref


def hdr_flip(estimate: ArrayLike, reference: ArrayLike) -> float | None:
    """Mean HDR-FLIP error (0 = identical) of linear images; ``None`` without flip-evaluator.

    Grayscale images are compared as gray RGB; both are scaled as :func:`flip_inputs` says.
    """
    try:
        import flip_evaluator
    except ImportError:
        return None
    x, ref = flip_inputs(*validate_pair(estimate, reference))
    _, mean_error, _ = flip_evaluator.evaluate(ref, x, "HDR", applyMagma=False)
    return float(mean_error)


def evaluate(
    estimate: ArrayLike,
    reference: ArrayLike,
    winding: ArrayLike | None = None,
    winding_ref: ArrayLike | None = None,
    *,
    flip: bool = True,
) -> dict[str, float]:
    """Every metric that applies: winding accuracy when both winding maps are given,
    SSIM/MS-SSIM when the image is at least 11 x 11, HDR-FLIP when installed and
    ``flip`` is true (it is slow: seconds for 256 x 256 on one core)."""
    if (winding is None) != (winding_ref is None):
        raise InvalidInputError(
            "winding accuracy needs both the estimated and the reference winding maps"
        )
    x, ref = validate_pair(estimate, reference)
    results: dict[str, float] = {}
    if winding is not None:
        results["winding_accuracy"] = winding_accuracy(winding, winding_ref)
    results["psnr"] = psnr(x, ref)
    results["pu21_psnr"] = pu21_psnr(x, ref)
    if min(x.shape[:2]) >= SSIM_WINDOW:
        results["ssim"] = ssim(x, ref)
        results["ms_ssim"] = ms_ssim(x, ref)
    flip_error = hdr_flip(x, ref) if flip else None
    if flip_error is not None:
        results["hdr_flip"] = flip_error
    return results
