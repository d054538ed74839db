"""Golden tests of the classical decoders (models/decoders/classical.py): where they are
exact (neighbours within half a wrap, the Itoh condition) and where they stop."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from models.decoders.base import anchor_winding
from models.decoders.classical import (
    HerraezDecoder,
    ItohDecoder,
    least_squares_unwrap,
    relative_winding,
    reliability_unwrap,
    specs,
)
from models.decoders.registry import get_decoder
from models.errors import McamError
from models.formation import SensorParams, encode, reconstruct, simulate

DECODERS = ["itoh", "herraez"]
SIZE = 256


def _radius2(size: int = SIZE) -> np.ndarray:
    yy, xx = np.mgrid[:size, :size]
    return (yy - size // 2) ** 2 + (xx - size // 2) ** 2


def gaussian_blob(encoding: str, peak_u: float = 20.5, sigma: float | None = None) -> np.ndarray:
    """x of a Gaussian blob whose unwrapped value u peaks at ``peak_u`` (alpha = 2).

    The default widths keep the steepest neighbour step below 0.4 wraps.
    """
    if encoding == "modulo":
        return peak_u * np.exp(-_radius2() / (2 * (sigma or 36.0) ** 2))
    return 2.0 ** (peak_u - 1) * np.exp(-_radius2() / (2 * (sigma or 20.0) ** 2))


def _params(encoding: str, bits: int = 8) -> SensorParams:
    return SensorParams(encoding=encoding, alpha=2.0, bits=bits)


def _max_step(winding: np.ndarray, codes: np.ndarray, bits: int) -> float:
    u = winding + (codes + 0.5) / 2**bits
    return float(max(np.abs(np.diff(u, axis=0)).max(), np.abs(np.diff(u, axis=1)).max()))


@pytest.mark.parametrize("encoding", ["modulo", "mantissa"])
@pytest.mark.parametrize("name", DECODERS)
def test_smooth_blob_peaking_at_20_wraps_is_recovered_exactly(name: str, encoding: str) -> None:
    params = _params(encoding)
    frame = encode(gaussian_blob(encoding), params)
    assert frame.winding.max() == 20
    assert _max_step(frame.winding, frame.codes, 8) < 0.5
    result = get_decoder(name).decode(frame.codes, params)
    assert result.winding.dtype == np.int64
    assert np.array_equal(result.winding, frame.winding)
    assert np.array_equal(result.irradiance, reconstruct(frame.codes, frame.winding, params))


@pytest.mark.parametrize("name", DECODERS)
@pytest.mark.parametrize(("step", "recovered"), [(0.45, True), (0.55, False), (2.1, False)])
def test_itoh_condition_a_step_above_half_a_wrap_is_not_recovered(
    name: str, step: float, recovered: bool
) -> None:
    """A disk brighter than its surround by ``step`` wraps (one sharp edge)."""
    background = 0.8 if step < 1 else 0.1
    x = np.where(_radius2() < 60**2, background + step, background)
    params = _params("modulo")
    frame = encode(x, params)
    result = get_decoder(name).decode(frame.codes, params)
    assert np.array_equal(result.winding, frame.winding) == recovered


@pytest.mark.parametrize("encoding", ["modulo", "mantissa"])
@pytest.mark.parametrize("name", DECODERS)
def test_steep_blob_breaks_the_itoh_condition_and_is_not_recovered(
    name: str, encoding: str
) -> None:
    params = _params(encoding)
    frame = encode(gaussian_blob(encoding, sigma=6.0), params)
    assert _max_step(frame.winding, frame.codes, 8) > 0.5
    result = get_decoder(name).decode(frame.codes, params)
    wrapped = frame.winding > 0
    assert result.winding[SIZE // 2, SIZE // 2] < 10 < frame.winding[SIZE // 2, SIZE // 2]
    assert np.mean(result.winding[wrapped] == frame.winding[wrapped]) < 0.5


@pytest.mark.parametrize("name", DECODERS)
def test_anchoring_gives_the_darkest_pixels_w_zero(name: str) -> None:
    """A frame whose every pixel has wrapped 3+ times: W is only known up to a constant,
    and the decoder reports it relative to the darkest pixels."""
    params = _params("modulo")
    frame = encode(3.2 + gaussian_blob("modulo", peak_u=5.0), params)
    assert frame.winding.min() == 3
    result = get_decoder(name).decode(frame.codes, params)
    assert np.array_equal(result.winding, frame.winding - 3)


@pytest.mark.parametrize("name", DECODERS)
def test_winding_is_clamped_to_max_wraps(name: str) -> None:
    params = SensorParams(encoding="modulo", bits=8, max_wraps=4.0)
    frame = encode(gaussian_blob("modulo", peak_u=4.0), params)
    result = get_decoder(name).decode(frame.codes, params.model_copy(update={"max_wraps": 2.0}))
    assert result.winding.max() == 2
    assert np.array_equal(result.winding, np.minimum(frame.winding, 2))


@pytest.mark.parametrize("name", DECODERS)
def test_rgb_is_decoded_per_channel(name: str) -> None:
    params = _params("modulo")
    scene = np.stack([gaussian_blob("modulo", peak_u=p) for p in (5.5, 11.5, 20.5)], axis=2)
    frame = simulate(scene, params)
    result = get_decoder(name).decode(frame.codes, frame.params)
    assert result.winding.shape == (SIZE, SIZE, 3)
    assert [int(result.winding[..., c].max()) for c in range(3)] == [5, 11, 20]
    assert np.array_equal(result.winding, frame.winding)
    green = get_decoder(name).decode(frame.codes[..., 1], frame.params)
    assert np.array_equal(green.winding, result.winding[..., 1])


@pytest.mark.parametrize("name", DECODERS)
def test_clip_encoding_decodes_to_w_zero(name: str) -> None:
    params = _params("clip")
    x = gaussian_blob("modulo", peak_u=3.0)
    frame = encode(x, params)
    result = get_decoder(name).decode(frame.codes, params)
    assert not result.winding.any()
    assert np.abs(result.irradiance - np.minimum(x, 1.0)).max() <= 2.0**-9


@pytest.mark.parametrize("name", DECODERS)
def test_result_reports_timings_and_decoder(name: str) -> None:
    params = _params("mantissa")
    frame = encode(gaussian_blob("mantissa", peak_u=3.0), params)
    result = get_decoder(name).decode(frame.codes[:32, :48], params)
    assert result.irradiance.shape == (32, 48)
    assert set(result.timings_ns) == {"predict", "invert", "total"}
    assert result.timings_ns["total"] >= result.timings_ns["predict"] >= 0
    assert result.info["decoder"] == name


@pytest.mark.parametrize("name", DECODERS)
@pytest.mark.parametrize(
    ("codes", "message"),
    [
        (np.zeros((0, 0), np.uint8), "0 x 0 frame has no neighbours"),
        (np.zeros((1, 1), np.uint8), "1 x 1 frame has no neighbours"),
        (np.zeros((1, 64), np.uint8), "1 x 64 frame has no neighbours"),
        (np.zeros((64,), np.uint8), "H x W or H x W x 3"),
        (np.zeros((8, 8, 4), np.uint8), "1 or 3 channels"),
        (np.full((8, 8), 0.5), "codes must be integers"),
        (np.full((8, 8), 256, np.uint16), "64 codes are >= 2\\^8"),
    ],
)
def test_bad_frames_get_clear_errors(name: str, codes: np.ndarray, message: str) -> None:
    with pytest.raises(McamError, match=message):
        get_decoder(name).decode(codes, _params("modulo"))


@pytest.mark.parametrize("decoder", [ItohDecoder(), HerraezDecoder()])
def test_predict_winding_checks_its_plane(decoder) -> None:
    with pytest.raises(McamError, match="one H x W channel"):
        decoder.predict_winding(np.zeros((4, 4, 3)), _params("modulo"))
    with pytest.raises(McamError, match="NaN or inf"):
        decoder.predict_winding(np.full((4, 4), np.nan), _params("modulo"))


@pytest.mark.parametrize("unwrap", [least_squares_unwrap, reliability_unwrap])
def test_unwrappers_recover_a_ramp_up_to_a_constant(unwrap) -> None:
    yy, xx = np.mgrid[:40, :50]
    u = 0.13 * xx + 0.07 * yy + 0.3
    m = u - np.floor(u)
    recovered = unwrap(m)
    assert np.allclose(recovered - recovered[0, 0], u - u[0, 0], atol=1e-9)
    assert np.array_equal(
        relative_winding(recovered, m) - relative_winding(recovered, m)[0, 0],
        np.floor(u).astype(np.int64),
    )


def test_specs_offer_both_decoders_as_classical() -> None:
    offered = {spec.name: spec for spec in specs()}
    assert set(offered) == {"itoh", "herraez"}
    assert {spec.kind for spec in offered.values()} == {"classical"}
    assert isinstance(offered["itoh"].factory(), ItohDecoder)
    assert isinstance(offered["herraez"].factory(), HerraezDecoder)


def smooth_u(rows: int, cols: int, seed: int, largest_step: float, floor: float) -> np.ndarray:
    """A random unwrapped field (wraps) from ``floor`` up, whose largest step between
    neighbours (across rows or columns) is ``largest_step``: integrated noise, so it
    spans many wraps."""
    field = np.random.default_rng(seed).standard_normal((rows, cols)).cumsum(0).cumsum(1)
    steps = max(np.abs(np.diff(field, axis=0)).max(), np.abs(np.diff(field, axis=1)).max())
    return floor + (field - field.min()) * largest_step / steps


@settings(max_examples=60, deadline=None)
@given(
    shape=st.tuples(st.integers(2, 32), st.integers(2, 32)),
    seed=st.integers(0, 2**32 - 1),
    largest_step=st.floats(0.01, 0.49),
    floor=st.floats(0.0, 3.0),
    bits=st.sampled_from([8, 12, 16]),
)
def test_itoh_is_exact_whenever_every_neighbour_step_is_under_half_a_wrap(
    shape: tuple[int, int], seed: int, largest_step: float, floor: float, bits: int
) -> None:
    """The Itoh condition as a property: over random fields of any size and range whose
    measured u (W + the codes' bin centre) steps less than half a wrap between any two
    neighbours, the unwrapping gives W exactly up to one constant, and the decoder's W
    is the truth anchored as it anchors (its lower tail at 0, clipped at 0: a few
    darker pixels below the tail read 0)."""
    params = SensorParams(encoding="modulo", bits=bits)
    frame = encode(smooth_u(*shape, seed, largest_step, floor), params)
    assert _max_step(frame.winding, frame.codes, bits) < 0.5  # quantising adds < 2^-bits
    m = (frame.codes + 0.5) / 2**bits
    relative = relative_winding(least_squares_unwrap(m), m)
    assert np.unique(relative - frame.winding).size == 1
    result = ItohDecoder().decode(frame.codes, params)
    assert np.array_equal(result.winding, anchor_winding(frame.winding, params))
