"""Saturated blobs: pixels clipped at the sensor's ``max_wraps`` all read one known value.

The image formation model (:func:`models.formation.encode`) clips irradiance at
``max_wraps`` before encoding, so every clipped pixel stores ``u_max =
u(max_wraps)`` (wraps): its code is ``frac(u_max)`` up to the sensor's noise (for
``max_wraps = 16`` and alpha 2, ``u_max`` is 5 on mantissa frames and 16 on modulo
ones, and the code is 0). A lamp, the sun or a specular highlight brighter than the
clip is such a plateau, and the plateau's border is a ring of steep, aliased wraps:
no path from the rest of the frame reaches it under the Itoh condition, so no
unwrapper can count its wraps from the codes, and every decoder leaves it several
wraps short (val-256 mantissa: the clipped pixels are 478 a frame in 16 of 24 frames,
with 39% of auto-best's squared error; set right, auto-best would gain 2.9 dB, 24.30
-> 27.22 dB).

:func:`fill_saturated` puts ``W = round(u_max - m)`` on every compact blob of pixels
that read the clip value, that the decoder already thinks is overexposed, and that an
aliased ring cuts off from the rest of the frame:

- a blob is a 4-connected set of pixels whose ``m`` lies within
  :func:`clip_tolerance` of ``frac(u_max)`` (wrapped distance; quantisation plus
  :data:`NOISE_SIGMAS` sigmas of the sensor's noise at the clip);
- of at least :data:`MIN_PIXELS` pixels, of which at least :data:`MIN_INTERIOR` are
  interior (all four neighbours in the blob): a wrap contour that happens to read the
  same code is a thin line, a clipped light a solid disc;
- at least :data:`MIN_BRIGHT_SHARE` of its pixels decoded at ``u = W + m >=``
  :data:`MIN_DECODED_U`: a dark patch (``x`` near 0 reads code 0 too, never code 255:
  read noise cannot take ``u`` below 0) is decoded at ``W = 0``. (Not ``W >= 1``:
  with read noise a blob the decoder puts at ``u`` near 1 is half ``W = 0`` at codes
  near 255.) A quarter, not half: the nets often decode only part of a lamp's flat
  core bright. Of the 159 blobs that pass the size and ring rules under auto-fast
  (2026-11-27: val-256 and 28 tuning crops, both encodings, read noise 0 and 0.01;
  the glows set; 24 synthetic 256x256 scenes with lobes), with either fast net,
  the dark ones below half had a bright share of at most 0.07 (4-5 blobs, 576-638
  px; 1-2 small dark blobs decoded bright pass either way), while 3-4 clipped blobs
  (1,943-3,247 px) lay between 0.25 and 0.5 (and, with small-s2d, 3 more of 982 px
  below 0.25). Half to a quarter, auto-fast with small-s2d: val-256 mantissa 22.60
  -> 22.76 dB, tuning crops mantissa 24.22 -> 24.35 dB; with tiny-s2d tuning modulo
  23.82 -> 24.27 dB and the lamp of ``tests/worker/test_clip_tracking.py`` filled
  (its core was 36% bright); auto-balanced and auto-best unchanged on every set (within 0.01 dB).
- and most of the pixels round it near residues (:func:`aliased_rings`): with read
  noise the tolerance grows, and wide wrap contours of gentle gradients (a band at
  ``u`` near 1, half ``W = 0`` and half ``W = 1``) and flat regions near a whole
  number of wraps read the clip's code too; they are reached smoothly.

The constants were chosen on the tuning crops of the training scenes (auto-balanced,
mean PSNR, read noise 0 / 0.005 / 0.01 / 0.02): mantissa 27.39 -> 29.28, 27.04 ->
28.83, 26.74 -> 28.41, 26.34 -> 27.95 dB; modulo 26.11 -> 28.08, 25.69 -> 27.59, 25.46
-> 27.31, 24.96 -> 26.68 dB. Without the ring rule the noisy crops lost up to 2.8 dB
at 3 sigmas (false blobs of 700-1000 px at ``u`` near 1); a ring share of 0.3-0.4 kept
a few more lamps than 0.5. On val-256 (2026-11-26, in ``auto``): mantissa fast /
balanced / best 21.95 / 24.02 / 24.30 -> 22.60 / 24.82 / 25.10 dB, modulo 22.13 /
24.01 / 24.06 -> 22.91 / 24.77 / 24.81 dB; at read noise 0.01 mantissa 21.90 / 23.62 /
24.31 -> 22.67 / 24.41 / 25.09 dB, modulo 21.22 / 23.02 / 23.89 -> 21.98 / 23.73 /
24.67 dB; the glows set +0.3-0.8 dB; the mostly-dark set and the synthetic 512x512
frames unchanged. About 1.5 ms a 256x256 frame.

A colour frame's channels are filled each on its own, then together
(:func:`fill_shared`; every decoder that fills clipped blobs runs it once the channels
are decoded, before they are joined, :func:`models.decoders.filling.filled_then_joined`).
Judged channel by channel, a white lamp clipped in all three could be filled in one
and left short in the others (auto-fast on a 128x128 mantissa frame of a lamp on a
dark textured background: x 0.02 / 0.36 / 16 wraps on its core, a blue lamp). Every
pixel of a blob filled in some channel (*overexposed*) is filled in each channel
where it lies in a blob that passes the size, interior and ring rules *in that
channel*, whatever that channel's decoder made of it: the bright share is the only
rule one channel lends another. A channel that does not read the clip there (a
coloured light clipping only one channel) keeps its own decision, and so does a
channel black under a coloured light (it reads the clip's code too, x near 0), whose
smooth surroundings leave no aliased ring: the channels' residues pooled would ring
it. That lamp: x 16.02 wraps in every channel, PSNR 18.98 -> 25.90 dB. bench.colour
(2026-11-28, mean PSNR and pixels with all three channels right; no frame lost over
0.01 dB): auto-fast val-256 mantissa 20.40 -> 20.46 dB (55.62 -> 55.65%), modulo 20.17
-> 20.22 dB, tuning crops modulo 23.36 -> 23.48 dB (one crop +3.0 dB), mantissa
23.78 -> 23.79 dB; auto-balanced and auto-best, whose join made most such lamps white already,
within 0.01 dB. About 5 ms a 256x256 colour frame (the three channels' own fills, 3.6
ms, on the same loaded host).

Failure modes: a clipped blob of fewer than :data:`MIN_PIXELS` pixels, or one the
decoder left at ``W = 0`` on more than three quarters of its pixels (both fast nets do
so with the flat core of a lamp on a dark textured background in a 64x64 frame: it
reads code 0 like a dark patch), stays short; so does
one whose ring is smooth enough to leave few residues (a clip reached by a gentle
slope, which an unwrapper can count anyway). A bright flat region cut off by steep
edges whose true ``u`` happens to sit at the clip's code (within the tolerance) and
that the decoder decoded as bright is raised to the clip, an error of up to ``u_max``
wraps on it. In a colour frame, a channel whose part of a lamp's core is cut off by a
smooth ring stays short while the others are filled (a white lamp of peak 40 wraps,
sigma 4 px, on the same textured background: red 0.61 wraps on the core); and a
channel black (within the tolerance of ``x = 0``) under a light clipped in another,
next to steep texture that rings it with residues (a pure-colour emitter in front of
a textured wall, with no crosstalk between the colour filters) is filled to the clip.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy import ndimage

from models.decoders.classical import wrap_difference
from models.formation import (
    MAX_WINDING,
    SensorParams,
    clip_winding,
    to_unwrapped,
    unwrapped_noise_sigma,
)
from models.scene_analysis import residue_pixels

#: A blob needs at least this many pixels...
MIN_PIXELS = 8
#: ...at least this fraction of them interior (all four 4-neighbours in the blob)...
MIN_INTERIOR = 0.5
#: ...at least this share of them decoded at ``u = W + m`` of at least
#: :data:`MIN_DECODED_U` (wraps)...
MIN_BRIGHT_SHARE = 0.25
MIN_DECODED_U = 0.5
#: ...and at least this share of the pixels within :data:`RING` px round it (Chebyshev)
#: lying within :data:`RESIDUE_REACH` px of a residue: cut off by an aliased ring.
RING_RESIDUE_SHARE = 0.4
RING = 2
RESIDUE_REACH = 2
#: Noise sigmas of ``u`` at the clip within which a pixel reads the clip value.
NOISE_SIGMAS = 3.0
#: Plus this many code steps (half a step: the codes are bin centres; half a step of slack).
CODE_STEPS = 1.0

_CROSS = ndimage.generate_binary_structure(2, 1)
#: A channel's blobs (:func:`solid_blobs`): labels, count, sizes, which are solid.
Blobs = tuple[NDArray[np.int64], int, NDArray[np.int64], NDArray[np.bool_]]


def clipped_value(params: SensorParams) -> float | None:
    """``u_max = u(max_wraps)`` (wraps), what every clipped pixel stores; None without a
    clip, or with one past ``MAX_WINDING / 2`` wraps (a modulo ``max_wraps`` of 2^62 and
    more): :func:`models.formation.encode` refuses a pixel wrapped that often, so no
    frame holds one, and its W ``round(u_max - m)`` would overflow int64."""
    if params.max_wraps is None or params.encoding == "clip":
        return None
    u_max = float(to_unwrapped(np.array(params.max_wraps), params))
    return u_max if u_max <= float(MAX_WINDING) / 2 else None


def clip_tolerance(params: SensorParams, u_max: float) -> float:
    """How far (wraps, wrapped distance) a clipped pixel's ``m`` may lie from
    ``frac(u_max)``: :data:`CODE_STEPS` code steps plus :data:`NOISE_SIGMAS` sigmas of
    the sensor's noise at the clip."""
    sigma = float(unwrapped_noise_sigma(np.array(u_max), params))
    return CODE_STEPS / (1 << params.bits) + NOISE_SIGMAS * sigma


def reads_clip(m: NDArray[np.float64], params: SensorParams, u_max: float) -> NDArray[np.bool_]:
    """Pixels (H x W) whose ``m`` (wraps) is within :func:`clip_tolerance` of ``frac(u_max)``."""
    offset = wrap_difference(m - (u_max - np.floor(u_max)))
    return np.abs(offset) <= clip_tolerance(params, u_max)


def interior(mask: NDArray[np.bool_]) -> NDArray[np.bool_]:
    """Pixels of ``mask`` (H x W) whose four neighbours are all in it (the frame's edge
    counts as outside)."""
    inner = np.zeros(mask.shape, bool)
    inner[1:-1, 1:-1] = (
        mask[1:-1, 1:-1] & mask[:-2, 1:-1] & mask[2:, 1:-1] & mask[1:-1, :-2] & mask[1:-1, 2:]
    )
    return inner


def solid_blobs(candidates: NDArray[np.bool_]) -> Blobs:
    """The 4-connected blobs of ``candidates`` (H x W): their labels (0 outside), count,
    sizes (px, per label) and which are solid (at least :data:`MIN_PIXELS` pixels, of
    which :data:`MIN_INTERIOR` interior; label 0 never)."""
    labels, count = ndimage.label(candidates, structure=_CROSS)
    sizes = np.bincount(labels.ravel(), minlength=count + 1)
    inside = np.bincount(labels[interior(candidates)], minlength=count + 1)
    solid = (sizes >= MIN_PIXELS) & (inside >= MIN_INTERIOR * sizes)
    solid[0] = False
    return labels, count, sizes, solid


def ringed(
    labels: NDArray[np.int64], keep: NDArray[np.bool_], m: NDArray[np.float64], count: int
) -> NDArray[np.bool_]:
    """The pixels (H x W) of the blobs ``keep`` (per label) that an aliased ring cuts
    off (:func:`aliased_rings`)."""
    if keep.any():
        keep = keep & aliased_rings(np.where(keep[labels], labels, 0), m, count)
    return keep[labels]


def saturated_blobs(
    winding: NDArray[np.int64], candidates: NDArray[np.bool_], m: NDArray[np.float64]
) -> NDArray[np.bool_]:
    """The pixels (H x W) of the blobs of ``candidates`` that pass the module's rules
    (size, interior share, decoded ``u = winding + m``, an aliased ring round them in
    ``m``)."""
    return overexposed_blobs(solid_blobs(candidates), winding, m)


def overexposed_blobs(
    blobs: Blobs,
    winding: NDArray[np.int64],
    m: NDArray[np.float64],
) -> NDArray[np.bool_]:
    """The pixels (H x W) of the solid ``blobs`` (:func:`solid_blobs`) that at least
    :data:`MIN_BRIGHT_SHARE` of are decoded at ``u = winding + m >=``
    :data:`MIN_DECODED_U` (wraps) and that an aliased ring in ``m`` cuts off."""
    labels, count, sizes, keep = blobs
    bright = np.bincount(labels[winding + m >= MIN_DECODED_U], minlength=count + 1)
    return ringed(labels, keep & (bright >= MIN_BRIGHT_SHARE * sizes), m, count)


def aliased_rings(
    labels: NDArray[np.int64], m: NDArray[np.float64], count: int
) -> NDArray[np.bool_]:
    """Per label (0..count, 0 the background), whether the pixels within :data:`RING` px
    of its blob (not in a blob) lie near residues in at least :data:`RING_RESIDUE_SHARE`
    of cases. A clipped plateau's ring is aliased (val-256 and the tuning crops, read
    noise 0 to 0.01: a share of 0.6-1.0 for 95% of them); a flat region or a wide wrap
    contour that merely reads the clip's code is reached smoothly (0-0.39)."""
    # Only the blobs' surroundings matter: every residue loop that can reach a ring
    # pixel lies within RING + RESIDUE_REACH + 1 px of a blob.
    box = grown_box(labels > 0, RING + RESIDUE_REACH + 2)
    labels, m = labels[box], m[box]
    grown = ndimage.grey_dilation(labels, footprint=np.ones((2 * RING + 1,) * 2, bool))
    ring = (labels == 0) & (grown > 0)
    near = residue_pixels(m, RESIDUE_REACH)[ring]
    owner = grown[ring]
    total = np.bincount(owner, minlength=count + 1)
    hits = np.bincount(owner[near], minlength=count + 1)
    return hits >= RING_RESIDUE_SHARE * np.maximum(total, 1)


def grown_box(mask: NDArray[np.bool_], margin: int) -> tuple[slice, slice]:
    """The bounding box of ``mask`` (H x W, not empty) grown by ``margin`` px, in the frame."""
    rows, cols = np.flatnonzero(mask.any(axis=1)), np.flatnonzero(mask.any(axis=0))
    height, width = mask.shape
    return (
        slice(max(rows[0] - margin, 0), min(rows[-1] + margin + 1, height)),
        slice(max(cols[0] - margin, 0), min(cols[-1] + margin + 1, width)),
    )


def clip_winding_of(
    m: NDArray[np.float64], params: SensorParams, u_max: float
) -> NDArray[np.int64]:
    """The W (H x W, in the encoding's range) that puts each pixel of ``m`` at the clip:
    ``round(u_max - m)``."""
    return clip_winding(np.round(u_max - m).astype(np.int64), params)


def fill_saturated(
    winding: NDArray[np.int64],
    m: NDArray[np.float64],
    params: SensorParams,
    judged: NDArray[np.int64] | None = None,
) -> tuple[NDArray[np.int64], dict[str, Any]]:
    """``winding`` (int W, H x W) with every saturated blob of ``m`` (module doc) set to the
    clip, ``W = round(u_max - m)``; and the facts (the fraction of pixels filled and
    the fraction changed). ``judged`` (H x W; default ``winding``) is the decoder's W
    that tells whether a blob is overexposed. Without ``max_wraps`` nothing changes."""
    u_max = clipped_value(params)
    if u_max is None:
        return winding, {}
    decided = winding if judged is None else judged
    blobs = saturated_blobs(decided, reads_clip(m, params, u_max), m)
    if not blobs.any():
        return winding, {"filled_fraction": 0.0, "changed_fraction": 0.0}
    filled = np.where(blobs, clip_winding_of(m, params, u_max), winding)
    return filled, {
        "filled_fraction": float(blobs.mean()),
        "changed_fraction": float(np.mean(filled != winding)),
    }


def fill_shared(
    winding: NDArray[np.int64], planes: NDArray[np.float64], params: SensorParams
) -> tuple[NDArray[np.int64], dict[str, Any]]:
    """A colour frame's ``winding`` (int W, H x W x C, each channel filled on its own)
    with each clip filled in every channel that holds it (module doc, colour frames),
    and the facts (the fractions of pixels overexposed in some channel and of
    pixel-channels changed); unchanged with no facts where no channel holds a saturated
    blob, or without ``max_wraps``. ``planes`` (H x W x C) are the channels' ``m``
    (wraps)."""
    u_max = clipped_value(params)
    if u_max is None:
        return winding, {}
    channels = range(planes.shape[2])
    blobs = [solid_blobs(reads_clip(planes[:, :, c], params, u_max)) for c in channels]
    overexposed = np.logical_or.reduce(
        [overexposed_blobs(blobs[c], winding[:, :, c], planes[:, :, c]) for c in channels]
    )
    if not overexposed.any():
        return winding, {}
    shared = np.stack([cut_off(blobs[c], overexposed, planes[:, :, c]) for c in channels], axis=2)
    filled = np.where(shared, clip_winding_of(planes, params, u_max), winding)
    return filled, {
        "filled_fraction": float(overexposed.mean()),
        "changed_fraction": float(np.mean(filled != winding)),
    }


def cut_off(
    blobs: Blobs,
    overexposed: NDArray[np.bool_],
    m: NDArray[np.float64],
) -> NDArray[np.bool_]:
    """The ``overexposed`` pixels (H x W) of the solid ``blobs`` (:func:`solid_blobs`)
    that an aliased ring in ``m`` (wraps) cuts off, whatever their decoded W."""
    labels, count, _, keep = blobs
    touched = np.zeros(count + 1, bool)
    touched[labels[overexposed]] = True
    return ringed(labels, keep & touched, m, count) & overexposed
