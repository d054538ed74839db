"""Tests of worker/brightness.py: the global gain between frames and brightening u."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

from models.errors import InvalidInputError
from models.formation import SensorParams, dequantize, encode, to_unwrapped
from tests.worker.panning import smooth_scene
from worker.brightness import BrightnessConfig, brighten, frame_gain

MODULO = SensorParams(encoding="modulo", bits=10, max_wraps=16.0)
MANTISSA = SensorParams(encoding="mantissa", bits=10, max_wraps=16.0)


def planes(x: np.ndarray, params: SensorParams) -> tuple[np.ndarray, np.ndarray]:
    """``(u, m)`` of a noiseless frame of ``x`` as H x W x 1 arrays."""
    frame = encode(x, params)
    m = dequantize(frame.codes, params.bits)
    return (frame.winding + m)[:, :, None], m[:, :, None]


@pytest.mark.parametrize("params", [MODULO, MANTISSA], ids=["modulo", "mantissa"])
@pytest.mark.parametrize("stops", [0.2, -0.3, 0.13])
def test_a_global_gain_is_found(params: SensorParams, stops: float) -> None:
    """The frame is the previous one times 2^stops: that gain (to the grid step) is found,
    and brightening the previous u with it predicts the current u."""
    scene = 0.3 * smooth_scene(64, 64)
    prev_u, _ = planes(scene, params)
    now_u, now_m = planes(scene * 2.0**stops, params)
    config = BrightnessConfig()
    gain, cost = frame_gain(prev_u, now_m, params, config)
    assert np.log2(gain) == pytest.approx(stops, abs=config.step)
    predicted = brighten(prev_u, gain, params)
    assert np.abs(predicted - now_u).max() < 0.1
    unchanged = frame_gain(prev_u, now_m, params, BrightnessConfig(search=0.0))
    assert unchanged[0] == 1.0 and cost < config.switch * unchanged[1]


@pytest.mark.parametrize("params", [MODULO, MANTISSA], ids=["modulo", "mantissa"])
def test_a_gain_is_kept_only_when_its_misfit_is_below_switch_times_no_changes(
    params: SensorParams,
) -> None:
    """With r the best gain's misfit over the misfit with no change, a switch just above r
    keeps the gain, one just below keeps 1 (and the misfit with no change)."""
    scene = 0.3 * smooth_scene(64, 64)
    prev_u, _ = planes(scene, params)
    _, now_m = planes(scene * 2.0**0.2, params)
    gain, cost = frame_gain(prev_u, now_m, params, BrightnessConfig(switch=1.0))
    _, unchanged = frame_gain(prev_u, now_m, params, BrightnessConfig(search=0.0))
    ratio = cost / unchanged
    assert gain != 1.0 and 0.0 < ratio < 1.0
    above, below = BrightnessConfig(switch=ratio * 1.01), BrightnessConfig(switch=ratio * 0.99)
    assert frame_gain(prev_u, now_m, params, above) == (gain, cost)
    assert frame_gain(prev_u, now_m, params, below) == (1.0, unchanged)


@pytest.mark.parametrize("params", [MODULO, MANTISSA], ids=["modulo", "mantissa"])
def test_no_change_or_no_search_gives_gain_one(params: SensorParams) -> None:
    u, m = planes(smooth_scene(64, 64), params)
    assert frame_gain(u, m, params, BrightnessConfig()) == (1.0, pytest.approx(0.0, abs=1e-3))
    _, brighter = planes(1.2 * smooth_scene(64, 64), params)
    assert frame_gain(u, brighter, params, BrightnessConfig(search=0.0))[0] == 1.0
    clip = SensorParams(encoding="clip")
    assert frame_gain(np.minimum(u, 1.0), m, clip, BrightnessConfig())[0] == 1.0


@settings(max_examples=40, deadline=None)
@given(x=st.floats(0.0, 20.0), gain=st.floats(0.5, 2.0))
def test_brighten_is_the_formation_model_at_the_gained_exposure(x: float, gain: float) -> None:
    """brighten(u(x), k) = u(min(k x, max_wraps)) for both encodings; gain 1 is identity."""
    for params in (MODULO, MANTISSA):
        u = to_unwrapped(np.array([min(x, 16.0)]), params)
        expected = to_unwrapped(np.array([min(gain * min(x, 16.0), 16.0)]), params)
        np.testing.assert_allclose(brighten(u, gain, params), expected, rtol=1e-9, atol=1e-12)
        assert brighten(u, 1.0, params) is u


@pytest.mark.filterwarnings("error")
@settings(max_examples=40, deadline=None)
@given(top=st.floats(1e300, 1.79e308), steps=st.integers(5, 25))  # bin centres fit float64
@example(top=1.7e308, steps=15)
def test_a_darkening_near_the_top_of_float64_is_found(top: float, steps: int) -> None:
    """Mantissa frames (no clip) whose brightest third sits at ``top``, then darkened by
    ``steps`` grid steps: a tried gain above 1 took those pixels past float64, their u to
    inf and the costs to NaN (numpy's overflow and invalid warnings), and argmin stopped
    at the first NaN: gain 1 with a misfit of 0.3 wraps for a 0.3-stop darkening."""
    params = SensorParams(encoding="mantissa", bits=10)
    rows, cols = np.mgrid[0:64, 0:64]
    x = np.exp(np.log(1e-3) + (np.log(top) - np.log(1e-3)) * np.minimum((rows + cols) / 84, 1))
    gain = 2.0 ** (-BrightnessConfig().step * steps)
    u, _ = planes(x, params)
    _, darker = planes(gain * x, params)
    found, cost = frame_gain(u, darker, params, BrightnessConfig())
    assert found == pytest.approx(gain) and cost < 0.01


@pytest.mark.parametrize("shape", [(1, 5, 1), (5, 1, 1), (2, 2, 1), (3, 7, 3)])
def test_tiny_and_colour_frames_do_not_crash(shape: tuple[int, ...]) -> None:
    u = np.full(shape, 1.3)
    m = np.full(shape, 0.3)
    assert frame_gain(u, m, MODULO, BrightnessConfig())[0] == 1.0
    assert brighten(u, 1.5, MODULO).shape == shape


@pytest.mark.parametrize(
    "bad", [{"search": -0.1}, {"search": 5.0}, {"step": 0.0}, {"stride": 0}, {"switch": 1.5}]
)
def test_bad_brightness_settings_are_refused(bad: dict) -> None:
    with pytest.raises(InvalidInputError, match="invalid brightness settings"):
        BrightnessConfig(**bad)
