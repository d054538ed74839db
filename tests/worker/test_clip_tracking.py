"""Tests of worker/clip_tracking.py: a moving clipped lamp filled where it goes, its
trail decoded spatially, blobs the temporal rule tracked left alone."""

from __future__ import annotations

import numpy as np
import pytest

from models.decoders.registry import get_decoder
from models.decoders.saturation import clip_tolerance, reads_clip
from models.errors import InvalidInputError
from models.formation import SensorParams
from worker.clip_tracking import ClipTrackConfig, continuing_blobs, track_clip
from worker.motion import misfit
from worker.temporal import StreamDecoder, decode_frames
from worker.temporal_config import TemporalConfig

PARAMS = SensorParams(encoding="modulo", bits=8, max_wraps=16)
SIZE = 128
#: The lamp's peak (wraps) and width (px): clipped at 16 within about 11 px of its centre.
PEAK, SIGMA = 40.0, 8.0


def lamp_u(cy: float, cx: float) -> np.ndarray:
    """u (wraps) of a clipped Gaussian lamp on a flat 0.3-wrap background."""
    yy, xx = np.mgrid[0:SIZE, 0:SIZE].astype(np.float64)
    lamp = PEAK * np.exp(-((yy - cy) ** 2 + (xx - cx) ** 2) / (2 * SIGMA**2))
    return np.minimum(0.3 + lamp, float(PARAMS.max_wraps))


def wrapped(u: np.ndarray) -> np.ndarray:
    """m (wraps) of ``u`` at the sensor's 8 bits (bin centres)."""
    return (np.floor((u - np.floor(u)) * 256) + 0.5) / 256


def tracked(previous_u: np.ndarray, m: np.ndarray) -> np.ndarray:
    """The temporal rule's W for ``m`` from ``previous_u``."""
    return np.rint(previous_u - m).astype(np.int64)


def itoh(crop: np.ndarray) -> np.ndarray:
    return get_decoder("itoh").predict_winding(crop, PARAMS)


def moved_lamp() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The previous u (lamp at x = 52), this frame's m (x = 64) and its true W."""
    previous, current = lamp_u(64, 52), lamp_u(64, 64)
    m = wrapped(current)
    return previous, m, np.rint(current - m).astype(np.int64)


def test_a_moving_lamp_is_filled_where_it_arrives_and_its_trail_is_decoded() -> None:
    previous, m, truth = moved_lamp()
    winding = tracked(previous, m)
    clipped = lamp_u(64, 64) >= PARAMS.max_wraps
    left = (lamp_u(64, 52) >= PARAMS.max_wraps) & (lamp_u(64, 64) < 1.0)
    assert (winding[clipped] != truth[clipped]).mean() > 0.2
    assert (winding[left] != truth[left]).all()
    result, taken = track_clip(
        m, winding, previous, misfit(previous, m), PARAMS, itoh, ClipTrackConfig()
    )
    np.testing.assert_array_equal(result[clipped], truth[clipped])
    np.testing.assert_array_equal(result[left], truth[left])
    assert taken[clipped].all() and taken[left].all()
    far = np.ones(m.shape, bool)
    far[20:110, 20:110] = False
    assert not taken[far].any()
    np.testing.assert_array_equal(result[~taken], winding[~taken])


def test_a_blob_the_rule_tracked_is_left_to_it() -> None:
    """The same blob, its new pixels at a noise-sized misfit (a sunrise's wrap contour
    at the clip's code is tracked exactly), is not filled."""
    previous, m, _ = moved_lamp()
    reads = reads_clip(m, PARAMS, 16.0)
    was_clipped = previous >= 16.0 - clip_tolerance(PARAMS, 16.0)
    config = ClipTrackConfig()
    jumped = continuing_blobs(m, was_clipped, misfit(previous, m), reads, config)
    assert jumped.sum() > 300
    still = continuing_blobs(m, was_clipped, np.full(m.shape, 0.01), reads, config)
    assert not still.any()


@pytest.mark.parametrize(
    ("params", "config", "previous"),
    [
        (PARAMS.model_copy(update={"max_wraps": None}), ClipTrackConfig(), lamp_u(64, 52)),
        (PARAMS, ClipTrackConfig(reach=0), lamp_u(64, 52)),
        (PARAMS, ClipTrackConfig(), np.full((SIZE, SIZE), 0.3)),
    ],
    ids=["no clip", "turned off", "nothing clipped before"],
)
def test_nothing_changes_without_a_clip_a_reach_or_a_clipped_previous_frame(
    params: SensorParams, config: ClipTrackConfig, previous: np.ndarray
) -> None:
    m = wrapped(lamp_u(64, 64))
    winding = tracked(previous, m)
    result, taken = track_clip(m, winding, previous, misfit(previous, m), params, itoh, config)
    np.testing.assert_array_equal(result, winding)
    assert not taken.any()


def test_a_lamp_switched_on_far_from_any_clip_is_not_filled() -> None:
    previous = lamp_u(30, 30)
    current = np.maximum(lamp_u(30, 30), lamp_u(96, 96))
    m = wrapped(current)
    winding = tracked(previous, m)
    result, taken = track_clip(
        m, winding, previous, misfit(previous, m), PARAMS, itoh, ClipTrackConfig()
    )
    assert not taken[70:, 70:].any()
    np.testing.assert_array_equal(result[70:, 70:], winding[70:, 70:])


@pytest.mark.parametrize("spatial", ["auto-fast", "itoh", "herraez", "mantissanet-tiny"])
def test_a_stream_keeps_a_moving_lamp_filled(spatial: str) -> None:
    """auto-fast fills the first frame's lamp; without clip tracking the temporal steps
    leave the lamp's new pixels short and its old core high (all of both, three
    frames on). A stream fills it with decoders that do not fill clipped blobs too: it
    kept their first frame's W on the lamp's core (bench.video's moving light: 0.05-0.54
    dB below decoding each frame alone)."""
    centres = (40, 52, 64, 76)
    codes = [np.floor(wrapped(lamp_u(64, x)) * 256).astype(np.uint8) for x in centres]
    truth = np.floor(lamp_u(64, centres[-1])).astype(np.int64)
    clipped = lamp_u(64, centres[-1]) >= PARAMS.max_wraps
    old_core = (lamp_u(64, centres[0]) >= PARAMS.max_wraps) & (lamp_u(64, centres[-1]) < 1.0)
    wrong = {}
    for name, clip in (("on", ClipTrackConfig()), ("off", ClipTrackConfig(reach=0))):
        decoder = StreamDecoder("temporal", spatial, TemporalConfig(clip=clip))
        *_, result = decode_frames(codes, PARAMS, decoder)
        wrong[name] = result.winding != truth
    assert wrong["off"][clipped].all() and wrong["off"][old_core].all()
    assert not wrong["on"][clipped].any() and not wrong["on"][old_core].any()
    assert wrong["on"].sum() < wrong["off"].sum()


@pytest.mark.parametrize(
    ("values", "fragment"),
    [
        ({"reach": -1}, "clip reach"),
        ({"misfit": 0.6}, "clip misfit"),
        ({"zone": -2}, "clip zone"),
        ({"wake": -1}, "clip wake"),
        ({"margin": -1}, "clip margin"),
    ],
)
def test_bad_knobs_are_refused_with_the_reason(values: dict[str, float], fragment: str) -> None:
    with pytest.raises(InvalidInputError, match=fragment):
        ClipTrackConfig(**values)  # type: ignore[arg-type]
