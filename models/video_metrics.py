"""Quality of a reconstructed clip against its ground truth, frame by frame and over time.

Clips are ``T x H x W`` (or ``T x H x W x 3``) linear HDR values on one scale
(wrap units); winding maps are ``T x H x W[x3]`` int64. Per-frame metrics come
from :mod:`models.metrics` and are averaged over frames:

- ``psnr`` / ``pu21_psnr``: mean per-frame PSNR in dB, each frame's at most
  :data:`models.metrics.PSNR_CAP` (an exact frame's inf counts as the cap);
- ``winding_accuracy``: fraction of all pixels of all frames with the right W;
- ``temporal_consistency``: mean absolute difference between the frame-to-frame
  changes of the tonemapped reconstruction and of the tonemapped truth (Reinhard,
  one key for the whole clip: the middle truth frame's), in display units [0, 1);
  0 means the reconstruction changes exactly as the truth does;
- ``wrap_flicker``: fraction of pixel transitions (pixel, t -> t+1) where the
  decoded W changes while the true W does not.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from models.errors import InvalidInputError
from models.metrics import mean_capped_psnr, psnr, pu21_psnr, reinhard, winding_accuracy


def _check_clips(estimate: ArrayLike, reference: ArrayLike) -> tuple[NDArray, NDArray]:
    """Both clips as arrays of the same shape with at least two frames."""
    est, ref = np.asarray(estimate), np.asarray(reference)
    if est.shape != ref.shape:
        raise InvalidInputError(
            f"the clip's shape {est.shape} does not match the reference's {ref.shape}; "
            "compare clips with the same frames, size and channels"
        )
    if est.ndim not in (3, 4) or est.shape[0] < 2:
        raise InvalidInputError(
            f"a clip is T x H x W[x3] with at least 2 frames, got shape {est.shape}"
        )
    return est, ref


def mean_psnr(estimate: ArrayLike, reference: ArrayLike) -> float:
    """Mean per-frame linear PSNR (dB), each frame peak = its reference maximum."""
    est, ref = _check_clips(estimate, reference)
    return mean_capped_psnr(psnr(e, r) for e, r in zip(est, ref, strict=True))


def mean_pu21_psnr(estimate: ArrayLike, reference: ArrayLike) -> float:
    """Mean per-frame PU21-PSNR (dB)."""
    est, ref = _check_clips(estimate, reference)
    return mean_capped_psnr(pu21_psnr(e, r) for e, r in zip(est, ref, strict=True))


def temporal_consistency(estimate: ArrayLike, reference: ArrayLike) -> float:
    """Mean |change of tonemapped estimate - change of tonemapped reference| over
    consecutive frames and pixels (display units, 0 = changes exactly like the truth)."""
    est, ref = _check_clips(estimate, reference)
    key = ref[ref.shape[0] // 2]
    tone_est = np.stack([reinhard(frame, key) for frame in est])
    tone_ref = np.stack([reinhard(frame, key) for frame in ref])
    return float(np.mean(np.abs(np.diff(tone_est, axis=0) - np.diff(tone_ref, axis=0))))


def wrap_flicker(winding: ArrayLike, winding_ref: ArrayLike) -> float:
    """Fraction of (pixel, t -> t+1) transitions where W changes but the true W does not."""
    w, w_ref = _check_clips(winding, winding_ref)
    if w.dtype.kind not in "iu" or w_ref.dtype.kind not in "iu":
        raise InvalidInputError(
            f"winding numbers must be integers, got {w.dtype} and {w_ref.dtype}"
        )
    flips = np.diff(w, axis=0) != 0
    true_flips = np.diff(w_ref, axis=0) != 0
    return float(np.mean(flips & ~true_flips))


def clip_metrics(
    estimate: ArrayLike, reference: ArrayLike, winding: ArrayLike, winding_ref: ArrayLike
) -> dict[str, float]:
    """Every clip metric of the module docstring, by name."""
    est, ref = _check_clips(estimate, reference)
    w, w_ref = _check_clips(winding, winding_ref)
    return {
        "psnr": mean_psnr(est, ref),
        "pu21_psnr": mean_pu21_psnr(est, ref),
        "winding_accuracy": winding_accuracy(w, w_ref),
        "temporal_consistency": temporal_consistency(est, ref),
        "wrap_flicker": wrap_flicker(w, w_ref),
    }
