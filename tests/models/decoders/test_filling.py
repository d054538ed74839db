"""Tests of models/decoders/filling.py: a decoder wrapped to fill clipped blobs."""

from __future__ import annotations

import numpy as np
import pytest

from models.decoders import get_decoder
from models.decoders.filling import FillingDecoder, filling
from models.formation import SensorParams, encode
from tests.models.decoders.colour_lamp import colour_lamp
from tests.models.decoders.fixed_planes import FixedPlanesDecoder

PARAMS = SensorParams(encoding="mantissa", bits=8, max_wraps=16.0, seed=3)


def lamp_scene() -> np.ndarray:
    """64 x 64 irradiance (wrap units): a gentle ramp and a lamp far past the clip."""
    rows, cols = np.mgrid[0:64, 0:64].astype(np.float64)
    lamp = 2000.0 * np.exp(-((rows - 32) ** 2 + (cols - 32) ** 2) / 32)
    return 0.2 + 2.3 * cols / 64 + lamp


@pytest.mark.parametrize("inner", ["itoh", "herraez", "mantissanet-tiny-s2d"])
def test_the_clipped_lamp_is_filled_and_the_rest_is_the_inner_decoders(inner: str) -> None:
    truth = encode(lamp_scene(), PARAMS)
    clipped = truth.irradiance >= PARAMS.max_wraps
    alone = get_decoder(inner).decode(truth.codes, PARAMS)
    wrapped = filling(get_decoder(inner))
    result = wrapped.decode(truth.codes, PARAMS)
    assert (alone.winding[clipped] != truth.winding[clipped]).any()
    np.testing.assert_array_equal(result.winding[clipped], truth.winding[clipped])
    np.testing.assert_array_equal(result.winding[~clipped], alone.winding[~clipped])
    assert result.info["details"]["saturation"]["filled_fraction"] > 0
    assert (result.info["decoder"], result.info["version"]) == (inner, alone.info["version"])


def test_a_decoder_that_fills_is_kept_and_one_that_does_not_is_wrapped() -> None:
    auto = get_decoder("auto-fast")
    assert filling(auto) is auto
    itoh = filling(get_decoder("itoh"))
    assert isinstance(itoh, FillingDecoder) and itoh.fills_saturation


def test_the_encodings_and_colour_handling_are_the_inner_decoders() -> None:
    """mantissanet-tiny-noise has a model for mantissa frames only; +colour joins
    channels."""
    tiny = filling(get_decoder("mantissanet-tiny-noise"))
    assert tiny.supports(SensorParams(encoding="mantissa"))
    assert not tiny.supports(SensorParams(encoding="modulo"))
    colour = get_decoder("itoh+colour")
    truth = encode(np.stack([lamp_scene()] * 3, axis=2), PARAMS)
    joined = filling(colour).decode(truth.codes, PARAMS)
    assert "colour" in joined.info
    assert joined.winding.shape == truth.winding.shape


def test_a_white_lamp_filled_in_one_channel_is_filled_in_every_channel() -> None:
    """The inner decoder calls the lamp's core dark (W = 0) in red and green and bright
    (3 wraps short) in blue: each channel filled on its own, the lamp came out blue."""
    frame, _, clipped = colour_lamp()
    decoded = np.where(clipped, 0, frame.winding)
    decoded[:, :, 2] = np.where(clipped[:, :, 2], frame.winding[:, :, 2] - 3, decoded[:, :, 2])
    result = filling(FixedPlanesDecoder(decoded)).decode(frame.codes, frame.params)
    core = clipped.all(axis=2)
    np.testing.assert_array_equal(result.winding[core], frame.winding[core])
    assert result.info["colour"]["saturation"]["changed_fraction"] > 0
