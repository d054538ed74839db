"""Tests of models/decoders/graphcut.py: PUMA graph-cut unwrapping."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from models.decoders.graphcut import GraphCutDecoder, PumaEnergy, clique_energy, puma_unwrap
from models.decoders.registry import available_decoders, get_decoder
from models.errors import InvalidInputError
from models.formation import SensorParams, dequantize, encode


def _hill(size: int = 96, peak: float = 16.0) -> np.ndarray:
    """A smooth scene (wrap units) from 0.1 to ``peak``: many wraps, no aliasing."""
    yy, xx = np.mgrid[0:size, 0:size] / size
    return 0.1 + peak * np.exp(-((xx - 0.5) ** 2 + (yy - 0.45) ** 2) / 0.08)


@pytest.mark.parametrize("encoding", ["modulo", "mantissa"])
@pytest.mark.parametrize("start", ["itoh", "zeros"])
def test_smooth_multi_wrap_scene_is_recovered_exactly(encoding: str, start: str) -> None:
    params = SensorParams(encoding=encoding, max_wraps=16)
    frame = encode(_hill(), params)
    assert frame.winding.max() >= 4
    result = GraphCutDecoder(start=start).decode(frame.codes, params)
    np.testing.assert_array_equal(result.winding, frame.winding)
    assert result.winding.dtype == np.int64
    assert result.info["decoder"] == "graphcut"
    assert result.info["details"]["energy"] <= result.info["details"]["start_energy"]


def test_zero_start_makes_one_move_per_wrap() -> None:
    m = dequantize(encode(_hill(64, 6.0), SensorParams(encoding="modulo")).codes, 8)
    result = puma_unwrap(m)
    assert len(result.energies) - 1 == 6
    assert result.moves == len(result.energies)
    assert result.winding.min() == 0


@settings(max_examples=15, deadline=None)
@given(
    m=arrays(np.float64, (12, 10), elements=st.floats(0.0, 0.999)),
    p=st.sampled_from([0.5, 1.0, 2.0]),
)
def test_energy_never_increases(m: np.ndarray, p: float) -> None:
    result = puma_unwrap(m, p=p, jumps=(2, 1))
    assert all(b < a for a, b in zip(result.energies, result.energies[1:], strict=False))
    assert clique_energy(result.winding + m, p) == pytest.approx(result.energies[-1])


@settings(max_examples=10, deadline=None)
@given(m=arrays(np.float64, (8, 8), elements=st.floats(0.0, 0.999)))
def test_convex_minimum_does_not_depend_on_start(m: np.ndarray) -> None:
    zero = puma_unwrap(m, p=2.0)
    shifted = puma_unwrap(m, p=2.0, start=np.arange(64).reshape(8, 8) % 3)
    assert shifted.energies[-1] == pytest.approx(zero.energies[-1])


def test_beats_itoh_on_a_noisy_scene() -> None:
    yy, xx = np.mgrid[0:64, 0:64].astype(float)
    scene = 0.2 + 3.0 * (1.0 + np.sin(xx / 6.0) * np.cos(yy / 7.0))
    params = SensorParams(encoding="modulo", read_noise=0.08, seed=3)
    frame = encode(scene, params)
    itoh = get_decoder("itoh").decode(frame.codes, params).winding
    graphcut = GraphCutDecoder().decode(frame.codes, params).winding
    itoh_accuracy = float(np.mean(itoh == frame.winding))
    graphcut_accuracy = float(np.mean(graphcut == frame.winding))
    assert graphcut_accuracy > 0.99
    assert graphcut_accuracy > itoh_accuracy + 0.2


def test_documented_failure_a_jump_over_half_a_wrap_is_aliased() -> None:
    """A real cliff of 1.6 wraps: every neighbour-difference method (PUMA too) reads it as
    -0.4 wraps, so the pixels beyond it are two wraps low."""
    yy, xx = np.mgrid[0:32, 0:32].astype(float)
    scene = 0.5 + 0.08 * xx + np.where(yy >= 16, 1.6, 0.0)
    params = SensorParams(encoding="modulo")
    frame = encode(scene, params)
    winding = GraphCutDecoder().decode(frame.codes, params).winding
    np.testing.assert_array_equal(winding[:16], frame.winding[:16])
    np.testing.assert_array_equal(winding[16:], frame.winding[16:] - 2)


def test_rgb_and_non_square_frames_keep_their_shape() -> None:
    params = SensorParams(encoding="mantissa", max_wraps=16)
    scene = _hill(48)[:, :40]
    frame = encode(np.stack([scene, scene * 0.5, scene * 0.25], axis=2), params)
    result = GraphCutDecoder().decode(frame.codes, params)
    assert result.winding.shape == (48, 40, 3)
    assert result.irradiance.shape == (48, 40, 3)
    np.testing.assert_array_equal(result.winding, frame.winding)
    assert len(result.info["channels"]) == 3


def test_registered_as_classical() -> None:
    spec = {s.name: s for s in available_decoders()}["graphcut"]
    assert spec.kind == "classical"
    assert isinstance(get_decoder("graphcut"), GraphCutDecoder)


@pytest.mark.parametrize(
    "m",
    [
        np.zeros(5),
        np.zeros((4, 4, 2)),
        np.zeros((1, 8)),
        np.full((4, 4), np.nan),
        np.full((4, 4), 1.5),
        np.full((4, 4), -0.1),
        np.zeros((4, 4), np.uint8),
    ],
)
def test_bad_wrapped_maps_are_rejected(m: np.ndarray) -> None:
    with pytest.raises(InvalidInputError):
        puma_unwrap(m)


@pytest.mark.parametrize(
    "kwargs",
    [
        {"p": 0.0},
        {"p": float("nan")},
        {"jumps": ()},
        {"jumps": (0,)},
        {"jumps": (1.5,)},
        {"max_moves": 0},
        {"start": "random"},
    ],
)
def test_bad_settings_are_rejected(kwargs: dict) -> None:
    with pytest.raises(InvalidInputError):
        GraphCutDecoder(**kwargs)


@pytest.mark.parametrize("start", [np.zeros((3, 4), np.int64), np.zeros((4, 4))])
def test_bad_start_maps_are_rejected(start: np.ndarray) -> None:
    with pytest.raises(InvalidInputError, match="start winding map"):
        puma_unwrap(np.zeros((4, 4)), start=start)


def test_decode_rejects_a_frame_without_neighbours() -> None:
    with pytest.raises(InvalidInputError, match="no neighbours"):
        GraphCutDecoder().decode(np.zeros((1, 9), np.uint8), SensorParams())


@pytest.mark.parametrize("above", [0.0, 0.5, 1.0, 2.0])
def test_the_prior_costs_above_factor_per_wrap_above_the_guess(above: float) -> None:
    """Each wrap below the prior costs prior_weight, each wrap above it above_factor
    times that; a move's cost per pixel is the difference of the two."""
    prior = np.array([[2, 2, 2]])
    energy = PumaEnergy(1.0, None, prior, 0.1, above)
    flat = np.zeros((1, 3))
    winding = np.array([[0, 2, 5]])
    prior_term = energy(winding, flat) - clique_energy(winding + flat, 1.0)
    assert prior_term == pytest.approx(0.1 * (2 + 3 * above))
    np.testing.assert_allclose(
        energy.prior_move_cost(winding, 1), 0.1 * np.array([[-1.0, above, above]])
    )
    np.testing.assert_allclose(
        energy.prior_move_cost(winding, -1), 0.1 * np.array([[1.0, 1.0, -above]])
    )


def test_a_prior_weight_per_pixel_weighs_each_pixels_disagreement() -> None:
    """One weight per pixel (colour anchors: weight on a few pixels, none elsewhere)
    gives the sum of each pixel's weighted cost, and the same moves."""
    prior = np.array([[2, 2, 2]])
    weights = np.array([[0.0, 0.5, 0.1]])
    energy = PumaEnergy(1.0, None, prior, weights, 1.0)
    flat = np.zeros((1, 3))
    winding = np.array([[0, 1, 5]])
    prior_term = energy(winding, flat) - clique_energy(winding + flat, 1.0)
    assert prior_term == pytest.approx(0.5 * 1 + 0.1 * 3)
    np.testing.assert_allclose(energy.prior_move_cost(winding, 1), [[0.0, -0.5, 0.1]])
