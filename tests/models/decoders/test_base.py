"""The decoder interface (models/decoders/base.py): shape checks, anchoring, dispatch."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest
from hypothesis import example, given
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from models.decoders.base import (
    ANCHOR_PERCENTILE,
    Decoder,
    anchor_winding,
    check_frame_shape,
    integer_percentile,
)
from models.decoders.classical import ItohDecoder
from models.decoders.registry import get_decoder
from models.errors import InvalidInputError, OutputOverflowError
from models.formation import SensorParams, encode

MODULO = SensorParams(encoding="modulo", bits=8)


class ConstantDecoder(Decoder):
    """Predicts one winding number everywhere and reports the plane's mean m."""

    name = "constant"

    def __init__(self, winding: int) -> None:
        self.winding = winding

    def predict_winding(self, m: np.ndarray, params: SensorParams) -> np.ndarray:
        return np.full(m.shape, self.winding, np.int64)

    def explain_winding(
        self, m: np.ndarray, params: SensorParams
    ) -> tuple[np.ndarray, dict[str, Any]]:
        return self.predict_winding(m, params), {"mean_m": float(m.mean())}


@pytest.mark.parametrize("shape", [(2, 2), (2, 5), (3, 2, 1), (4, 4, 3)])
def test_frames_of_2x2_and_more_with_1_or_3_channels_pass(shape: tuple[int, ...]) -> None:
    check_frame_shape(np.zeros(shape, np.uint8))


@pytest.mark.parametrize(
    ("shape", "message"),
    [
        ((5,), "H x W or H x W x 3"),
        ((2, 2, 2, 2), "H x W or H x W x 3"),
        ((4, 4, 2), "1 or 3 channels"),
        ((4, 4, 4), r"H x W x 3 \(RGB without its alpha channel\)"),
        ((1, 9), "1 x 9 frame has no neighbours"),
        ((9, 1, 3), "9 x 1 frame"),
    ],
)
def test_frames_a_decoder_cannot_unwrap_are_rejected(shape: tuple[int, ...], message: str) -> None:
    with pytest.raises(InvalidInputError, match=message):
        check_frame_shape(np.zeros(shape, np.uint8))


@pytest.mark.parametrize("shape", [(3, 64, 48), (1, 64, 48), (4, 64, 48)])
def test_a_frame_stored_channels_first_is_told_to_move_them_last(
    shape: tuple[int, ...],
) -> None:
    """A 3 x H x W array (a tensor's layout) was refused as "a frame has 1 or 3
    channels, got shape (3, 64, 48)", though it has 3: the refusal names the layout."""
    with pytest.raises(InvalidInputError) as caught:
        check_frame_shape(np.zeros(shape, np.uint8))
    message = str(caught.value)
    assert f"stored channels first ({shape[0]} x H x W)" in message
    assert "with its channels last (H x W x C)" in message


def test_a_small_frame_of_2_channels_is_not_called_channels_first() -> None:
    with pytest.raises(InvalidInputError) as caught:
        check_frame_shape(np.zeros((4, 4, 2), np.uint8))
    assert "channels first" not in str(caught.value)


@pytest.mark.parametrize(
    ("shape", "remedy"),
    [
        ((1, 1), "send the whole frame$"),
        ((1, 40), r"send the whole frame, or this row twice \(a 2 x 40 frame\)"),
        ((40, 1, 3), r"send the whole frame, or this column twice \(a 40 x 2 frame\)"),
    ],
)
def test_a_frame_one_pixel_wide_is_refused_saying_what_to_send(
    shape: tuple[int, ...], remedy: str
) -> None:
    """A 1 x N frame was refused as having 'no neighbours to unwrap against' (each pixel
    has two, along the row) with nothing to do about it."""
    with pytest.raises(InvalidInputError, match=remedy):
        check_frame_shape(np.zeros(shape, np.uint8))


def test_a_row_sent_twice_decodes_as_that_row() -> None:
    """What the refusal of a 1 x N frame advises works: each copy gets the row's W."""
    row = encode(np.linspace(0.01, 20.0, 64)[None, :], MODULO)
    result = ItohDecoder().decode(np.vstack([row.codes, row.codes]), MODULO)
    np.testing.assert_array_equal(result.winding, np.vstack([row.winding, row.winding]))


def test_anchor_shifts_the_darkest_pixels_to_zero() -> None:
    relative = np.array([[-3, -3, -2], [-1, 0, 4]])
    assert np.array_equal(anchor_winding(relative, MODULO), relative + 3)


def test_anchor_ignores_rare_outliers_and_clamps_them_to_zero() -> None:
    relative = np.full((100, 100), 5, np.int64)
    relative[:, 50:] = 7
    outliers = int(relative.size * ANCHOR_PERCENTILE / 100) - 1
    relative.flat[:outliers] = -40
    anchored = anchor_winding(relative, MODULO)
    assert anchored.flat[outliers:].min() == 0
    assert anchored.max() == 2
    assert np.all(anchored.flat[:outliers] == 0)


def test_anchor_clamps_to_max_winding() -> None:
    relative = np.arange(12).reshape(3, 4)
    assert anchor_winding(relative, MODULO.model_copy(update={"max_wraps": 4.0})).max() == 4
    assert not anchor_winding(relative, SensorParams(encoding="clip")).any()


def test_decoder_is_abstract() -> None:
    with pytest.raises(TypeError):
        Decoder()  # type: ignore[abstract]


def test_single_channel_stack_keeps_its_shape() -> None:
    frame = encode(np.linspace(0, 3, 64).reshape(8, 8, 1), MODULO)
    result = ItohDecoder().decode(frame.codes, MODULO)
    assert result.winding.shape == (8, 8, 1)
    assert np.array_equal(result.winding, frame.winding)


def test_explanations_are_reported_per_channel() -> None:
    codes = np.zeros((4, 4, 3), np.uint8)
    codes[..., 1] = 128
    info = ConstantDecoder(0).decode(codes, MODULO).info
    assert info["decoder"] == "constant"
    assert [c["mean_m"] for c in info["channels"]] == [0.5 / 256, 128.5 / 256, 0.5 / 256]
    single = ConstantDecoder(0).decode(codes[..., 1], MODULO).info
    assert single["details"] == {"mean_m": 128.5 / 256}


def test_inversion_uses_predicted_winding() -> None:
    codes = np.full((3, 3), 64, np.uint8)
    result = ConstantDecoder(2).decode(codes, SensorParams(encoding="mantissa", alpha=2.0))
    assert np.allclose(result.irradiance, 2.0 ** (2 + 64.5 / 256 - 1))


def test_clip_frames_skip_prediction() -> None:
    result = ConstantDecoder(7).decode(
        np.full((3, 3), 255, np.uint8), SensorParams(encoding="clip")
    )
    assert not result.winding.any()
    assert "details" not in result.info


def test_absurd_winding_is_an_overflow_error_not_inf() -> None:
    params = SensorParams(encoding="mantissa", alpha=2.0)
    with pytest.raises(OutputOverflowError, match="9 pixels"):
        ConstantDecoder(5000).decode(np.zeros((3, 3), np.uint8), params)


@given(
    arrays(np.int64, st.integers(1, 300), elements=st.integers(-40, 40)),
    st.floats(0.0, 100.0),
)
@example(np.array([0] + [1] * 51), 5e-324)
def test_integer_percentile_matches_numpy_higher(values: np.ndarray, percentile: float) -> None:
    expected = np.percentile(values, percentile, method="higher")
    assert integer_percentile(values, percentile) == expected


@pytest.mark.parametrize("name", ["mantissanet-small", "mantissanet-small-noise+puma", "itoh"])
def test_every_decoder_takes_a_clip_frame_which_never_wraps(name: str) -> None:
    """W is 0 for a clipped sensor whatever the decoder: decode gave it, yet a learned
    decoder said it did not support clip frames, so the API refused what mcam decoded."""
    params = SensorParams(encoding="clip", bits=8)
    decoder = get_decoder(name)
    assert decoder.supports(params)
    codes = np.arange(64, dtype=np.uint8).reshape(8, 8)
    assert not decoder.decode(codes, params).winding.any()


def test_a_net_without_a_model_for_an_encoding_that_wraps_still_refuses_it() -> None:
    decoder = get_decoder("mantissanet-small-noise")
    assert decoder.supports(SensorParams(encoding="mantissa"))
    assert not decoder.supports(SensorParams(encoding="modulo"))
