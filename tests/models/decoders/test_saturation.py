"""Tests of models/decoders/saturation.py: clipped blobs set to the sensor's clip."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from models.decoders import get_decoder
from models.decoders.guided_puma import GuidedPumaDecoder
from models.decoders.saturation import (
    MIN_BRIGHT_SHARE,
    MIN_PIXELS,
    clip_tolerance,
    clipped_value,
    fill_saturated,
    fill_shared,
    reads_clip,
)
from models.formation import SensorParams, dequantize, encode, max_winding
from tests.models.decoders.colour_lamp import WHITE, colour_lamp

SIZE = 64


def _params(encoding: str = "mantissa", read_noise: float = 0.0) -> SensorParams:
    return SensorParams(
        encoding=encoding, bits=8, max_wraps=16.0, read_noise=read_noise, seed=3
    )


def _lamp(params: SensorParams, sigma: float = 4.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A gentle ramp (x 0.2-2.5 wraps) with a lamp far above the clip at its centre: the
    true W, ``m`` and the clipped pixels (x at ``max_wraps``)."""
    yy, xx = np.mgrid[0:SIZE, 0:SIZE].astype(np.float64)
    ramp = 0.2 + 2.3 * xx / SIZE
    lamp = 2000.0 * np.exp(-((yy - 32) ** 2 + (xx - 32) ** 2) / (2 * sigma**2))
    frame = encode(ramp + lamp, params)
    return frame.winding, dequantize(frame.codes, params.bits), frame.irradiance >= 16.0


def _under_counted(truth: np.ndarray, clipped: np.ndarray, short: int = 3) -> np.ndarray:
    """What a decoder leaves: the lamp's clipped core ``short`` wraps short."""
    return np.where(clipped, truth - short, truth)


@pytest.mark.parametrize("encoding", ["mantissa", "modulo"])
def test_a_clipped_lamp_gets_the_clip_value(encoding: str) -> None:
    params = _params(encoding)
    truth, m, clipped = _lamp(params)
    assert clipped.sum() > MIN_PIXELS
    filled, facts = fill_saturated(_under_counted(truth, clipped), m, params)
    np.testing.assert_array_equal(filled[clipped], truth[clipped])
    np.testing.assert_array_equal(filled[~clipped], truth[~clipped])
    assert facts["filled_fraction"] == pytest.approx(clipped.mean())
    assert facts["changed_fraction"] == pytest.approx(clipped.mean())
    assert filled.dtype == np.int64 and filled.shape == m.shape


def test_a_noisy_lamp_is_filled_on_both_sides_of_the_wrap() -> None:
    """With read noise the clip's u straddles a wrap: each pixel gets the W that puts its
    u nearest the clip."""
    params = _params(read_noise=0.01)
    truth, m, clipped = _lamp(params)
    filled, _ = fill_saturated(_under_counted(truth, clipped), m, params)
    u_max = clipped_value(params)
    assert u_max is not None
    inside = clipped & reads_clip(m, params, u_max)
    assert np.all(np.abs(filled[inside] + m[inside] - u_max) <= clip_tolerance(params, u_max))
    assert np.mean(filled[clipped] == truth[clipped]) > 0.95


def test_a_noisy_lamp_decoded_near_one_wrap_is_still_overexposed() -> None:
    """With read noise the core reads codes near 255 and near 0; a decoder that puts it
    at u near 1 gives half of it W = 0 (the codes near 255), yet it is bright."""
    params = _params(read_noise=0.01)
    truth, m, clipped = _lamp(params)
    near_one = np.where(clipped, np.where(m > 0.5, 0, 1), truth)
    assert np.mean(near_one[clipped] == 0) > 0.3
    filled, _ = fill_saturated(near_one, m, params)
    assert np.mean(filled[clipped] == truth[clipped]) > 0.95


def _partly_bright(clipped: np.ndarray, share: float, truth: np.ndarray) -> np.ndarray:
    """A decoder's W that calls the first ``share`` of the clipped pixels (row order)
    bright, 3 wraps short, and the rest dark (W = 0)."""
    rows, cols = np.nonzero(clipped)
    bright = np.zeros(clipped.shape, bool)
    take = int(np.ceil(share * rows.size))
    bright[rows[:take], cols[:take]] = True
    return np.where(bright, truth - 3, np.where(clipped, 0, truth))


@pytest.mark.parametrize(("share", "filled"), [(MIN_BRIGHT_SHARE, True), (0.1, False)])
def test_a_blob_is_overexposed_when_a_quarter_of_it_is_decoded_bright(
    share: float, filled: bool
) -> None:
    """The nets often call part of a lamp's flat core dark: a quarter decoded bright is
    enough; a blob the decoder calls dark but for a few pixels stays as decoded."""
    params = _params()
    truth, m, clipped = _lamp(params)
    guess = _partly_bright(clipped, share, truth)
    result, _ = fill_saturated(guess, m, params)
    expected = truth if filled else guess
    np.testing.assert_array_equal(result[clipped], expected[clipped])


def test_a_fill_can_be_judged_on_another_answer() -> None:
    """A refinement that lowered the blob to W = 0 hides it; judged on the unrefined
    answer it is filled all the same."""
    params = _params()
    truth, m, clipped = _lamp(params)
    lowered = np.where(clipped, 0, truth)
    unchanged, _ = fill_saturated(lowered, m, params)
    np.testing.assert_array_equal(unchanged, lowered)
    filled, _ = fill_saturated(lowered, m, params, judged=_under_counted(truth, clipped))
    np.testing.assert_array_equal(filled, truth)


def test_without_a_clip_nothing_changes() -> None:
    params = _params().model_copy(update={"max_wraps": None})
    truth, m, clipped = _lamp(_params())
    guess = _under_counted(truth, clipped)
    filled, facts = fill_saturated(guess, m, params)
    np.testing.assert_array_equal(filled, guess)
    assert facts == {}


@settings(max_examples=40, deadline=None)
@given(max_wraps=st.integers(min_value=16, max_value=2**1000).map(float))
@example(max_wraps=2.0**64)
def test_a_fill_puts_the_lamp_at_the_clip_or_leaves_it(max_wraps: float) -> None:
    """A modulo lamp clipped at a whole number of wraps reads code 0 at any clip; a filled
    pixel's ``u = W + m`` lies within half a wrap of ``u_max``. A clip past 2^63 wraps
    overflowed ``round(u_max - m)`` in int64 (a RuntimeWarning), and the lamp was
    "filled" to W = 0, as dark as the frame's darkest pixels."""
    truth, m, clipped = _lamp(_params("modulo"))
    guess = _under_counted(truth, clipped)
    params = _params("modulo").model_copy(update={"max_wraps": max_wraps})
    filled, _ = fill_saturated(guess, m, params)
    changed = filled != guess
    assert (filled >= guess).all()
    assert np.abs(filled[changed] + m[changed] - max_wraps).max(initial=0.0) <= max(
        0.5, max_wraps * 1e-15
    )


def test_a_dark_patch_that_reads_the_clip_code_stays_dark() -> None:
    """x near 0 reads code 0 as the clip does; the decoder calls it W = 0."""
    params = _params()
    m = np.full((SIZE, SIZE), 0.3)
    m[20:40, 20:40] = dequantize(np.zeros((20, 20), np.uint8), params.bits)
    winding = np.zeros(m.shape, np.int64)
    filled, facts = fill_saturated(winding, m, params)
    np.testing.assert_array_equal(filled, winding)
    assert facts["filled_fraction"] == 0.0


def test_a_bright_plateau_reached_smoothly_is_not_the_clip() -> None:
    """A flat bright region at a whole number of wraps, inside a smooth ramp (no residue
    round it), reads the clip's code but is not cut off from the frame."""
    params = _params()
    yy, xx = np.mgrid[0:SIZE, 0:SIZE].astype(np.float64)
    u = 1.5 + 0.02 * xx
    u[24:40, 24:40] = 2.0
    winding = np.floor(u).astype(np.int64)
    filled, _ = fill_saturated(winding, u - winding, params)
    np.testing.assert_array_equal(filled, winding)


def test_a_thin_contour_that_reads_the_clip_code_is_not_a_blob() -> None:
    params = _params()
    truth, m, clipped = _lamp(params)
    guess = _under_counted(truth, clipped)
    line = np.zeros(m.shape, bool)
    line[5, 2:60] = True
    m = np.where(line, m[clipped][0], m)
    guess = np.where(line, 1, guess)
    filled, _ = fill_saturated(guess, m, params)
    np.testing.assert_array_equal(filled[line], 1)


@settings(max_examples=40, deadline=None)
@given(
    codes=arrays(np.uint8, (12, 14), elements=st.sampled_from([0, 1, 40, 128, 250, 255])),
    winding=arrays(np.int64, (12, 14), elements=st.integers(0, 5)),
    encoding=st.sampled_from(["mantissa", "modulo"]),
)
def test_filling_changes_only_clip_readings_into_the_range_and_settles(
    codes: np.ndarray, winding: np.ndarray, encoding: str
) -> None:
    params = _params(encoding)
    m = dequantize(codes, params.bits)
    filled, _ = fill_saturated(winding, m, params)
    u_max = clipped_value(params)
    assert u_max is not None
    changed = filled != winding
    assert not np.any(changed & ~reads_clip(m, params, u_max))
    assert filled.min() >= 0 and filled.max() <= max(int(winding.max()), max_winding(params))
    again, _ = fill_saturated(filled, m, params)
    np.testing.assert_array_equal(again, filled)


@pytest.mark.parametrize("name", ["auto-balanced", "auto-best", "auto-balanced+puma"])
def test_auto_fills_a_clipped_lamp_and_reports_it(name: str) -> None:
    """(auto-fast's net calls this lamp's flat core dark, W = 0, so it stays: the
    module's failure mode.) Refined again (``+puma``), the lamp is filled again."""
    params = _params()
    yy, xx = np.mgrid[0:SIZE, 0:SIZE].astype(np.float64)
    texture = 0.6 + 0.5 * np.sin(xx / 3.0) * np.cos(yy / 5.0)
    lamp = 2000.0 * np.exp(-((yy - 32) ** 2 + (xx - 32) ** 2) / (2 * 4.0**2))
    frame = encode(texture + lamp, params)
    decoder = get_decoder(name)
    assert decoder.fills_saturation
    result = decoder.decode(frame.codes, params)
    clipped = frame.irradiance >= 16.0
    np.testing.assert_array_equal(result.winding[clipped], frame.winding[clipped])
    assert result.info["details"]["saturation"]["filled_fraction"] >= clipped.mean()


def test_a_refiner_refills_only_for_a_guide_that_fills() -> None:
    """``GuidedPumaDecoder.refilled`` puts a lamp lowered by a refinement back at the clip
    when its guide fills clipped blobs (``auto``), and leaves W alone otherwise."""
    params = _params()
    yy, xx = np.mgrid[0:SIZE, 0:SIZE].astype(np.float64)
    lamp = 2000.0 * np.exp(-((yy - 32) ** 2 + (xx - 32) ** 2) / (2 * 4.0**2))
    frame = encode(0.6 + lamp, params)
    m = dequantize(frame.codes, params.bits)
    clipped = frame.irradiance >= 16.0
    lowered = np.where(clipped, 0, frame.winding)
    filling = GuidedPumaDecoder(get_decoder("auto-balanced"))
    refilled, facts = filling.refilled(m, lowered, frame.winding, params)
    np.testing.assert_array_equal(refilled[clipped], frame.winding[clipped])
    assert facts is not None and facts["filled_fraction"] >= clipped.mean()
    plain = GuidedPumaDecoder(get_decoder("itoh"))
    kept, none = plain.refilled(m, lowered, frame.winding, params)
    np.testing.assert_array_equal(kept, lowered)
    assert none is None


def filled_per_channel(decoded: np.ndarray, m: np.ndarray, params: SensorParams) -> np.ndarray:
    """Each channel of ``decoded`` (H x W x 3) filled on its own, as a decoder does."""
    return np.stack(
        [fill_saturated(decoded[:, :, c], m[:, :, c], params)[0] for c in range(3)], axis=2
    )


def test_a_white_lamp_is_filled_in_every_channel_when_one_channel_fills_it() -> None:
    """A decoder that calls the lamp's core dark (W = 0) in red and green and bright
    (3 wraps short) in blue filled blue alone: the lamp came out blue."""
    frame, m, clipped = colour_lamp(size=SIZE, peak=2000.0)
    truth, params = frame.winding, frame.params
    core = clipped.all(axis=2)
    decoded = np.where(clipped, 0, truth)
    decoded[:, :, 2] = np.where(clipped[:, :, 2], truth[:, :, 2] - 3, truth[:, :, 2])
    alone = filled_per_channel(decoded, m, params)
    assert (alone[:, :, :2][core] == 0).all()
    np.testing.assert_array_equal(alone[:, :, 2][core], truth[:, :, 2][core])
    filled, facts = fill_shared(alone, m, params)
    np.testing.assert_array_equal(filled[clipped], truth[clipped])
    np.testing.assert_array_equal(filled[~clipped], alone[~clipped])
    assert facts["filled_fraction"] >= core.mean() and facts["changed_fraction"] > 0


@pytest.mark.parametrize("dark", [False, True])
def test_a_lamp_saturating_one_channel_leaves_the_others_as_decoded(dark: bool) -> None:
    """A blue lamp clips blue alone: blue keeps its own fill, red and green their decoded
    W, also where they are black and read the clip's code (x = 0) round the clipped
    blue."""
    frame, m, clipped = colour_lamp((0.002, 0.004, 1.0), size=SIZE, peak=2000.0, dark=dark)
    truth, params = frame.winding, frame.params
    assert clipped[:, :, 2].sum() > MIN_PIXELS and not clipped[:, :, :2].any()
    alone = filled_per_channel(np.where(clipped, truth - 3, truth), m, params)
    blue = clipped[:, :, 2]
    np.testing.assert_array_equal(alone[:, :, 2][blue], truth[:, :, 2][blue])
    filled, _ = fill_shared(alone, m, params)
    np.testing.assert_array_equal(filled[:, :, :2], truth[:, :, :2])
    np.testing.assert_array_equal(filled[:, :, 2], alone[:, :, 2])


def test_auto_fast_gives_a_white_lamp_one_clip_in_every_channel() -> None:
    """auto-fast's net called this lamp's core dark in red and green (x 0.02 and 0.36
    wraps) and filled blue (16 wraps): a blue lamp."""
    frame, _, clipped = colour_lamp(WHITE)
    result = get_decoder("auto-fast").decode(frame.codes, frame.params)
    core = clipped.all(axis=2)
    np.testing.assert_array_equal(result.winding[core], frame.winding[core])
    assert result.info["colour"]["saturation"]["changed_fraction"] > 0
