"""Frames a decoder reconstructs exactly (PSNR inf), to check how benchmarks average them."""

from __future__ import annotations

from models.decoders import get_decoder
from models.scenes import ValFrame, val256_frames


def exactly_decoded(frame: ValFrame, decoder: str = "itoh") -> ValFrame:
    """``frame`` with its truth ``x`` replaced by ``decoder``'s reconstruction (and its W)."""
    result = get_decoder(decoder).decode(frame.codes, frame.params)
    return frame._replace(x=result.irradiance, winding=result.winding)


def exact_and_wrong(encoding: str = "mantissa") -> list[ValFrame]:
    """Two val-256 frames: the first decoded exactly by itoh, the second as it is (itoh's
    PSNR on it is finite, about 20 dB)."""
    first, second = val256_frames(encoding)[:2]
    return [exactly_decoded(first), second]
