"""Bracketed reference capture: merge clipped exposures into a reference HDR, store the pair.

The camera sends a bracket as consecutive data packets flagged ``FLAG_BRACKET``:
index 0 is the wrapped frame, indices 1..n are conventional (``clip``) images
whose gain grows by a constant ratio. :func:`merge_exposures` is a
Debevec-style merge for a linear sensor: each exposure's estimate of the scene
``z / gain`` is weighted by a hat function of its code value ``z`` that is zero
for dark and saturated samples. :class:`BracketCollector` assembles the packets
and :func:`save_pair` writes a new folder of ``data_dir/datasets/<device>/``
(:mod:`device.datasets`: named by the host's clock, then the sequence; whole or not at all)
with ``wrapped.png`` (codes + params), ``reference.exr`` (scene-referred irradiance,
the wrapped frame's ``x`` is ``gain * reference``) and ``meta.json``.

A pixel saturated in every exposure (:func:`clipped_pixels`) has only a lower bound in
the reference; ``meta.json`` gives their share (``merge.clipped_fraction``), and a
bracket saturated at every pixel is not saved at all (:class:`SaturatedBracketError`):
its reference would be the darkest exposure's clip everywhere, a target that says
nothing of the scene the wrapped frame recorded.
"""

from __future__ import annotations

import json
import shutil
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from device.datasets import finish_pair, new_pair_folder
from device.link_protocol import FLAG_BRACKET, DataPacket
from models.errors import InvalidInputError
from models.formation import SensorParams, dequantize
from models.frames import write_frame
from models.hdr_io import write_exr

#: Hat weight support in normalised code units: samples below are dark, above saturated.
DARK_LEVEL = 0.02
SATURATION_LEVEL = 0.95


def hat_weight(z: NDArray[np.float64]) -> NDArray[np.float64]:
    """Debevec hat weight of normalised codes ``z`` in [0, 1]: 0 outside (dark, saturated)."""
    middle = (DARK_LEVEL + SATURATION_LEVEL) / 2
    half = (SATURATION_LEVEL - DARK_LEVEL) / 2
    return np.clip(1.0 - np.abs(z - middle) / half, 0.0, None)


class SaturatedBracketError(InvalidInputError):
    """Every pixel of a bracket is saturated in every exposure: its reference would hold
    only a lower bound, no measurement, so the pair is not saved."""


def _sorted_exposures(
    codes: Sequence[NDArray[np.unsignedinteger]], gains: Sequence[float], bits: int
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """The exposures' normalised codes (n x H x W, in [0, 1)) and gains (n x 1 x 1),
    darkest (lowest gain) first; fewer than two exposures or a gain <= 0 are refused."""
    if len(codes) != len(gains) or len(codes) < 2:
        raise InvalidInputError("a bracket needs at least two exposures, each with its gain")
    if any(g <= 0 for g in gains):
        raise InvalidInputError(f"bracket gains must be positive, got {list(gains)}")
    order = np.argsort(gains)
    z = np.stack([dequantize(codes[i], bits) for i in order])
    return z, np.asarray(gains, np.float64)[order].reshape(-1, *([1] * (z.ndim - 1)))


def merge_exposures(
    codes: Sequence[NDArray[np.unsignedinteger]], gains: Sequence[float], bits: int
) -> NDArray[np.float64]:
    """Scene-referred irradiance from clipped exposures (``x = gain * scene``, clipped at 1).

    Pixels with no usable sample take the darkest exposure's value where it is
    saturated (a lower bound, see :func:`clipped_pixels`) and the brightest exposure's
    value elsewhere.
    """
    z, g = _sorted_exposures(codes, gains, bits)
    weights = hat_weight(z)
    estimates = z / g
    total = weights.sum(axis=0)
    merged = (weights * estimates).sum(axis=0) / np.where(total > 0, total, 1.0)
    fallback = np.where(z[0] >= SATURATION_LEVEL, estimates[0], estimates[-1])
    return np.where(total > 0, merged, fallback)


def clipped_pixels(
    codes: Sequence[NDArray[np.unsignedinteger]], gains: Sequence[float], bits: int
) -> NDArray[np.bool_]:
    """The pixels (bool, H x W) saturated in every exposure: no sample inside the hat's
    support, the darkest exposure at or above :data:`SATURATION_LEVEL`. There
    :func:`merge_exposures` gives only a lower bound (the darkest exposure's clip)."""
    z, _ = _sorted_exposures(codes, gains, bits)
    return ~(hat_weight(z) > 0).any(axis=0) & (z[0] >= SATURATION_LEVEL)


@dataclass
class Bracket:
    """A complete bracket: the wrapped frame and the clipped exposures."""

    wrapped: DataPacket
    exposures: list[DataPacket]

    def reference(self) -> NDArray[np.float64]:
        """The merged scene-referred reference HDR."""
        return merge_exposures(*self._exposures())

    def clipped(self) -> NDArray[np.bool_]:
        """The pixels saturated in every exposure (:func:`clipped_pixels`)."""
        return clipped_pixels(*self._exposures())

    def _exposures(self) -> tuple[list[NDArray[np.unsignedinteger]], list[float], int]:
        """The exposures' codes, gains and their one bit depth; fewer than two refused."""
        if len(self.exposures) < 2:
            raise InvalidInputError(
                f"a bracket needs at least two clipped exposures, this one has "
                f"{len(self.exposures)} (the camera sent bracket count "
                f"{self.wrapped.bracket_count}: the wrapped frame and its exposures); request "
                "brackets of count 2 or more"
            )
        bits = {p.bits for p in self.exposures}
        if len(bits) != 1:
            raise InvalidInputError(f"bracket exposures mix bit depths {sorted(bits)}")
        return [p.codes for p in self.exposures], [p.gain for p in self.exposures], bits.pop()


class BracketCollector:
    """Assembles bracket packets; a gap or an interruption abandons the bracket."""

    def __init__(self) -> None:
        self._packets: list[DataPacket] = []
        self.abandoned = 0

    def add(self, packet: DataPacket) -> Bracket | None:
        """Take one data packet; return a bracket when this packet completes one. A packet
        out of order, or an exposure that does not fit the bracket (see :meth:`fits`),
        abandons it."""
        if not packet.flags & FLAG_BRACKET:
            return None
        expected = len(self._packets)
        if packet.bracket_index == 0:
            self._abandon()
            self._packets = [packet]
        elif (expected and packet.bracket_index == expected
              and packet.sequence == self._packets[-1].sequence + 1 and self.fits(packet)):
            self._packets.append(packet)
        else:
            self._abandon()
            return None
        if len(self._packets) == packet.bracket_count:
            wrapped, *exposures = self._packets
            self._packets = []
            return Bracket(wrapped, exposures)
        return None

    def fits(self, exposure: DataPacket) -> bool:
        """Whether ``exposure`` can join the bracket begun: a conventional (``clip``) image
        of the wrapped frame's size, at the bit depth of the exposures before it."""
        wrapped, *exposures = self._packets
        return (
            exposure.encoding == "clip"
            and exposure.codes.shape == wrapped.codes.shape
            and all(exposure.bits == earlier.bits for earlier in exposures)
        )

    def interrupt(self) -> None:
        """The link broke: an unfinished bracket cannot complete."""
        self._abandon()

    def _abandon(self) -> None:
        if self._packets:
            self.abandoned += 1
        self._packets = []


def save_pair(root: Path, device: str, bracket: Bracket) -> Path:
    """Write the (wrapped frame, reference HDR) pair in a new folder; return the folder.
    The pair is saved whole or not at all: when a file cannot be written (a reference
    float32 cannot hold, a full disk) the error is raised and no folder is left. A
    bracket saturated at every pixel is refused before anything is written
    (:func:`refuse_saturated`)."""
    refuse_saturated(bracket)
    folder = new_pair_folder(root, device, bracket.wrapped.sequence)
    try:
        write_pair(folder, device, bracket)
    except BaseException:
        shutil.rmtree(folder, ignore_errors=True)
        raise
    return finish_pair(folder)


def refuse_saturated(bracket: Bracket) -> None:
    """Raise :class:`SaturatedBracketError` when every pixel of ``bracket`` is saturated
    in every exposure (see the module docstring)."""
    if bracket.clipped().all():
        darkest = min(p.gain for p in bracket.exposures)
        raise SaturatedBracketError(
            f"every pixel is saturated, even in the bracket's darkest exposure (gain "
            f"{darkest:g}): its reference would hold only a lower bound, so no pair is "
            "saved; request the bracket again with a darker first exposure (a lower "
            "base_gain, or more exposures or a larger ratio)"
        )


def write_pair(folder: Path, device: str, bracket: Bracket) -> None:
    """Write ``wrapped.png``, ``reference.exr`` and ``meta.json`` of ``bracket`` in ``folder``."""
    wrapped = bracket.wrapped
    params = SensorParams.parse({"encoding": wrapped.encoding, "alpha": wrapped.alpha,
                                 "bits": wrapped.bits, "gain": wrapped.gain or None})
    reference = bracket.reference()
    write_frame(folder / "wrapped.png", wrapped.codes, params)
    write_exr(folder / "reference.exr", reference,
              {"comments": "bracketed reference, scene-referred; x = gain * value"})
    meta = {
        "device": device,
        "sequence": wrapped.sequence,
        "timestamp_ns": wrapped.timestamp_ns,
        "params": params.model_dump(),
        "exposure_gains": [p.gain for p in bracket.exposures],
        "merge": {"weights": "hat", "dark_level": DARK_LEVEL,
                  "saturation_level": SATURATION_LEVEL,
                  "clipped_fraction": float(bracket.clipped().mean())},
    }
    (folder / "meta.json").write_text(json.dumps(meta, indent=2))
