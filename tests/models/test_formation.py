"""Property and table tests of the image formation model (models/formation.py)."""

from __future__ import annotations

import contextlib
import math

import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

from models.decodable import check_decodable
from models.decoders import get_decoder
from models.errors import InvalidInputError, OutputOverflowError, OutputUnderflowError
from models.exposure import check_not_black, exposure_gain, luminance
from models.formation import (
    SensorParams,
    dequantize,
    encode,
    from_unwrapped,
    largest_noise_sigma,
    max_winding,
    quantize,
    reconstruct,
    simulate,
    split_unwrapped,
    to_scene,
    to_unwrapped,
    unwrapped_noise_sigma,
    validate_codes,
    validate_irradiance,
)

PROPERTY = settings(max_examples=200, deadline=None)
#: Largest winding number split_unwrapped accepts (half the int64 range, kept as headroom).
WINDING_LIMIT = 2**62

bits_st = st.integers(1, 16)
alpha_st = st.floats(1.001, 1000.0)
x_st = st.one_of(st.floats(0.0, 2.0), st.floats(0.0, 1e30))
x_arrays = st.lists(x_st, min_size=1, max_size=16).map(np.array)


def _round_trip(x: np.ndarray, params: SensorParams) -> np.ndarray:
    frame = encode(x, params)
    return reconstruct(frame.codes, frame.winding, params)


@PROPERTY
@given(x=x_arrays, bits=bits_st)
def test_modulo_round_trip_within_half_a_code(x: np.ndarray, bits: int) -> None:
    params = SensorParams(encoding="modulo", bits=bits)
    if np.floor(x).max() > WINDING_LIMIT:
        with pytest.raises(InvalidInputError, match="wrap more than"):
            encode(x, params)
        return
    error = np.abs(_round_trip(x, params) - x)
    assert np.all(error <= 2.0 ** -(bits + 1) + np.spacing(x))


@PROPERTY
@given(x=x_arrays, bits=bits_st, alpha=alpha_st)
def test_mantissa_round_trip_error_bounds(x: np.ndarray, bits: int, alpha: float) -> None:
    params = SensorParams(encoding="mantissa", alpha=alpha, bits=bits)
    x_hat = _round_trip(x, params)
    u = to_unwrapped(x, params)
    linear = u < 1
    assert np.all(np.abs(x_hat - x)[linear] <= 2.0 ** -(bits + 1))
    half_code = 2.0 ** -(bits + 1) + np.spacing(u[~linear])
    rounding = 4 * np.finfo(np.float64).eps * (1 + np.abs(np.log(x[~linear])))
    bound = np.expm1(half_code * math.log(alpha)) + rounding
    assert np.all(np.abs(x_hat[~linear] / x[~linear] - 1) <= bound)


@PROPERTY
@given(x=x_arrays, alpha=alpha_st)
def test_mantissa_u_is_monotonic(x: np.ndarray, alpha: float) -> None:
    params = SensorParams(encoding="mantissa", alpha=alpha)
    u = to_unwrapped(np.sort(x), params)
    assert np.all(np.diff(u) >= 0)


@PROPERTY
@given(alpha=alpha_st, delta=st.floats(1e-12, 1e-3))
def test_mantissa_u_is_continuous_at_saturation(alpha: float, delta: float) -> None:
    params = SensorParams(encoding="mantissa", alpha=alpha)
    x = np.array([1.0 - delta, 1.0, 1.0 + delta])
    below, at, above = to_unwrapped(x, params)
    step_below, step_above = 1.0 - x[0], x[2] - 1.0  # exact in float64
    assert at == 1.0
    assert at - below == step_below
    eps = np.finfo(np.float64).eps
    assert 0 < above - at <= step_above / math.log(alpha) + 2 * eps


@PROPERTY
@given(m=st.lists(st.floats(0.0, 1.0, exclude_max=True), min_size=1).map(np.array), bits=bits_st)
def test_quantize_then_dequantize_is_within_half_a_code(m: np.ndarray, bits: int) -> None:
    codes = quantize(m, bits)
    assert codes.dtype == (np.uint8 if bits <= 8 else np.uint16)
    assert int(codes.max()) < 2**bits
    assert np.all(np.abs(dequantize(codes, bits) - m) <= 2.0 ** -(bits + 1))


@pytest.mark.parametrize("bits", [1, 8, 9, 16])
def test_dequantize_then_quantize_returns_every_code(bits: int) -> None:
    codes = np.arange(2**bits, dtype=np.uint8 if bits <= 8 else np.uint16)
    assert np.array_equal(quantize(dequantize(codes, bits), bits), codes)


def test_negative_codes_are_counted_and_told_what_to_send() -> None:
    """Negative codes (a black level subtracted, a signed array) were refused as "codes
    must be non-negative, found -5", without how many or what to send instead."""
    with pytest.raises(InvalidInputError, match=r"found 2 below 0 \(min -5\)") as error:
        validate_codes(np.array([-5, -1, 3]), 8)
    assert "raw codes, 0 to 2^8 - 1, as read" in str(error.value)


def test_codes_past_16_bits_are_not_told_to_raise_bits() -> None:
    """Codes of 2^16 or more (scaled, or summed frames) were told "set bits to the
    sensor's real bit depth", which cannot exceed 16."""
    with pytest.raises(InvalidInputError, match=r"max 70000\); codes have 16 bits at most"):
        validate_codes(np.array([0, 70_000]), 8)
    with pytest.raises(InvalidInputError, match="set bits to the sensor's real bit depth"):
        validate_codes(np.array([0, 60_000]), 8)


def test_quantize_clamps_m_of_one_to_the_top_code() -> None:
    assert quantize(np.array([1.0]), 8)[0] == 255


@pytest.mark.parametrize(
    ("codes", "message"),
    [
        (np.array([], np.uint8), "empty"),
        (np.array([0.5, 0.2]), "integers"),
        (np.array([-1, 3]), "non-negative"),
        (np.array([0, 256], np.uint16), "1 codes are >= 2\\^8"),
    ],
)
def test_bad_codes_are_rejected(codes: np.ndarray, message: str) -> None:
    with pytest.raises(InvalidInputError, match=message):
        validate_codes(codes, 8)


@pytest.mark.parametrize("seed", [-1, 2**63])
def test_noise_seeds_must_be_non_negative_64_bit(seed: int) -> None:
    with pytest.raises(InvalidInputError, match="seed"):
        SensorParams.parse({"seed": seed})


@PROPERTY
@given(
    winding=st.lists(st.integers(0, 2**63 - 1), min_size=1, max_size=8).map(np.array),
    alpha=alpha_st,
    encoding=st.sampled_from(["modulo", "mantissa"]),
    dtype=st.sampled_from([np.float16, np.float32, np.float64]),
)
def test_reconstruction_never_overflows_silently(
    winding: np.ndarray, alpha: float, encoding: str, dtype: type[np.floating]
) -> None:
    params = SensorParams(encoding=encoding, alpha=alpha, bits=8)
    codes = np.full(winding.shape, 128, np.uint8)
    u = winding.astype(np.float64) + 128.5 / 256
    limit = float(np.finfo(dtype).max)
    over = u > limit
    if encoding == "mantissa":
        over = np.where(u >= 1, (u - 1) * np.log(alpha) > np.log(limit), over)
    n_over = int(np.sum(over))
    if n_over:
        with pytest.raises(
            OutputOverflowError, match=f"^{n_over} pixels .* {np.dtype(dtype).name}"
        ):
            reconstruct(codes, winding, params, dtype)
        return
    x_hat = reconstruct(codes, winding, params, dtype)
    assert x_hat.dtype == dtype
    assert np.all(np.isfinite(x_hat))


def test_largest_int64_winding_reconstructs_in_float64_modulo() -> None:
    winding = np.array([np.iinfo(np.int64).max])
    x_hat = reconstruct(np.array([0], np.uint8), winding, SensorParams(encoding="modulo"))
    assert x_hat[0] == pytest.approx(2.0**63)


def test_overflow_message_names_pixel_count_and_limit() -> None:
    params = SensorParams(encoding="mantissa", alpha=2.0, bits=8)
    winding = np.array([[200, 1], [0, 200]])
    with pytest.raises(
        OutputOverflowError, match=r"^2 pixels .*float32 limit 3\.403e\+38.*lower the gain or alpha"
    ):
        reconstruct(np.zeros((2, 2), np.uint8), winding, params, np.float32)
    with pytest.raises(
        OutputOverflowError, match=r"^1 pixels .*float16 limit 6\.55e\+04; ask for float32 output"
    ):
        from_unwrapped(np.array([70000.0, 3.0]), SensorParams(encoding="modulo"), np.float16)


def test_half_float_overflow_past_float32_too_is_not_told_to_use_float32() -> None:
    """alpha^(u-1) past float32 (u = 201, alpha 2) was told "ask for float32 output"."""
    params = SensorParams(encoding="mantissa", alpha=2.0, bits=8)
    with pytest.raises(OutputOverflowError, match="float16 limit .*; ask for float32 output"):
        reconstruct(np.zeros((1, 2), np.uint8), np.array([[20, 1]]), params, np.float16)
    with pytest.raises(
        OutputOverflowError, match="float16 limit .*; float32 output cannot hold them either: lower"
    ):
        reconstruct(np.zeros((1, 2), np.uint8), np.array([[200, 1]]), params, np.float16)


def test_a_reconstruction_that_would_round_to_zero_is_refused() -> None:
    """A huge gain (scene-referred x / gain) or half floats for tiny values: the EXR would
    be silently black, so the error names the count and what to change."""
    codes, winding = np.array([[3, 200]], np.uint8), np.zeros((1, 2), np.int64)
    huge_gain = SensorParams(encoding="mantissa", gain=1e308)
    with pytest.raises(
        OutputUnderflowError, match=r"^2 nonzero pixels .*float32.*gain 1e\+308.*lower the gain"
    ):
        reconstruct(codes, winding, huge_gain, np.float32, scene_referred=True)
    assert np.all(reconstruct(codes, winding, huge_gain, np.float64, scene_referred=True) > 0)
    tiny_scene = SensorParams(encoding="modulo", gain=1e9)
    with pytest.raises(OutputUnderflowError, match=r"^1 nonzero .*float16.*ask for float32"):
        reconstruct(codes[:, :1], winding[:, :1], tiny_scene, np.float16, scene_referred=True)
    assert reconstruct(codes[:, :1], winding[:, :1], tiny_scene, np.float16)[0, 0] > 0


def test_a_scene_referred_overflow_asks_for_a_higher_gain() -> None:
    """x / gain with a tiny gain overflows: lowering the gain would make it worse."""
    codes, winding = np.array([[3, 200]], np.uint8), np.zeros((1, 2), np.int64)
    tiny_gain = SensorParams(encoding="mantissa", gain=1e-40)
    with pytest.raises(OutputOverflowError, match=r"gain 1e-40.*a higher gain gives smaller"):
        reconstruct(codes, winding, tiny_gain, np.float32, scene_referred=True)


def test_too_many_wraps_for_int64_is_a_clear_error() -> None:
    with pytest.raises(InvalidInputError, match="1 pixels wrap more than"):
        split_unwrapped(np.array([1e30, 5.0]), SensorParams(encoding="modulo"))


def test_too_many_wraps_under_a_max_wraps_given_asks_to_lower_it() -> None:
    """It asked to "set max_wraps", which was set (1e20) and let x pass int64's W."""
    params = SensorParams(encoding="modulo", max_wraps=1e20)
    with pytest.raises(InvalidInputError) as caught:
        encode(np.array([[1e30, 5.0]]), params)
    message = caught.value.message
    assert "lower the gain, or max_wraps (1e+20) to at most 4611686018427387903" in message
    assert "set max_wraps" not in message


@pytest.mark.parametrize(
    ("value", "what"),
    [(np.nan, "NaN or infinite"), (np.inf, "NaN or infinite"), (-0.5, "negative")],
)
def test_bad_irradiance_is_rejected(value: float, what: str) -> None:
    scene = np.array([[0.1, value], [value, 0.3]])
    with pytest.raises(InvalidInputError, match=f"2 {what}"):
        encode(scene, SensorParams())
    with pytest.raises(InvalidInputError, match=f"2 {what}"):
        simulate(scene, SensorParams())


def test_clip_negative_zeroes_and_counts() -> None:
    scene = np.array([[0.5, -1e-3], [-2e-4, 2.0]])
    clipped, count = validate_irradiance(scene, clip_negative=True)
    assert count == 2
    assert np.array_equal(clipped, [[0.5, 0.0], [0.0, 2.0]])
    frame = simulate(scene, SensorParams(encoding="modulo"), clip_negative=True)
    assert np.array_equal(frame.winding, [[0, 0], [0, 2]])


def test_a_float64_scene_is_checked_without_a_copy_and_never_changed() -> None:
    """The simulate path checked a scene three times (read, simulate, encode), each a
    float64 copy: a 4096 x 4096 RGB upload peaked at 3.5 GB."""
    scene = np.array([[0.5, 3.0], [2.0, 0.0]])
    assert validate_irradiance(scene)[0] is scene
    assert validate_irradiance(scene.astype(np.float16))[0].dtype == np.float64
    before = scene.copy()
    for encoding in ("modulo", "mantissa", "clip"):
        params = SensorParams(encoding=encoding, read_noise=0.1, full_well=100.0, seed=1)
        simulate(scene, params)
        encode(scene, params)
    assert np.array_equal(scene, before)
    negative = np.array([[0.5, -1e-3]])
    clipped, count = validate_irradiance(negative, clip_negative=True)
    assert count == 1 and clipped[0, 1] == 0.0 and negative[0, 1] == -1e-3


def test_the_frame_of_a_scene_is_exactly_the_formula_s() -> None:
    """u, W, m and the codes (computed in place to save full-size arrays) are the
    model's formulas written out, bit for bit."""
    x = np.random.default_rng(3).lognormal(0.0, 3.0, (40, 30))
    for encoding, alpha in (("modulo", 2.0), ("mantissa", 1.7)):
        params = SensorParams(encoding=encoding, alpha=alpha, bits=10)
        above = x >= 1.0
        log_part = 1.0 + np.log(np.where(above, x, 1.0)) / np.log(alpha)
        u = np.where(above, log_part, x) if encoding == "mantissa" else x
        frame = encode(x, params)
        assert np.array_equal(frame.winding, np.floor(u).astype(np.int64))
        m = u - np.floor(u)
        assert np.array_equal(frame.codes, np.clip(np.floor(m * 1024), 0, 1023))
        assert np.array_equal(to_unwrapped(x, params), u)
        assert np.array_equal(split_unwrapped(u, params)[1], m)


def test_empty_and_non_numeric_irradiance_are_rejected() -> None:
    with pytest.raises(InvalidInputError, match="empty"):
        validate_irradiance(np.zeros((0, 3)))
    with pytest.raises(InvalidInputError, match="real numbers"):
        validate_irradiance(np.array([1 + 2j]))


@PROPERTY
@given(data=st.data(), n=st.integers(4, 300), scale=st.floats(1e-6, 1e6))
def test_exposure_gain_overexposes_exactly_the_requested_fraction(
    data: st.DataObject, n: int, scale: float
) -> None:
    k = data.draw(st.integers(1, n - 1), label="overexposed pixels")
    rng = np.random.default_rng(data.draw(st.integers(0, 2**32 - 1), label="seed"))
    scene = (rng.permutation(n) + 1.0).reshape(1, n) * scale
    frame = simulate(scene, SensorParams(encoding="modulo"), overexposed=k / n)
    assert int(np.sum(frame.irradiance >= 1.0)) == k
    assert frame.params.gain == exposure_gain(scene, k / n)


@PROPERTY
@given(k=st.integers(1, 400), seed=st.integers(0, 2**32 - 1), scale=st.floats(1e-6, 1e6))
def test_the_pixel_at_the_exposure_quantile_reaches_saturation(
    k: int, seed: int, scale: float
) -> None:
    """With 5k + 1 pixels the 80 % quantile is a pixel value: that pixel must reach x >= 1."""
    n = 5 * k + 1
    scene = (np.random.default_rng(seed).permutation(n) + 1.0).reshape(1, n) * scale
    frame = simulate(scene, SensorParams(encoding="modulo"), overexposed=0.2)
    level = np.quantile(scene, 0.8)
    assert np.array_equal(frame.irradiance >= 1.0, scene >= level)


def test_exposure_of_rgb_uses_rec709_luminance() -> None:
    scene = np.zeros((2, 2, 3))
    scene[..., 1] = [[1.0, 2.0], [3.0, 4.0]]
    gain = exposure_gain(scene, 0.25)
    assert gain == pytest.approx(1.0 / np.quantile(0.7152 * np.array([1, 2, 3, 4.0]), 0.75))
    assert luminance(np.ones((1, 1, 3)))[0, 0] == pytest.approx(1.0)


@pytest.mark.parametrize(
    ("overexposed", "fragment"),
    [
        (1.0, "got 1: every pixel, the darkest included"),
        (1.5, "got 1.5, more than every pixel (for 1.5%, give 0.015)"),
        (250.0, "got 250, more than every pixel:"),
        (np.inf, "got inf, more than every pixel"),
        (0.0, "got 0, which overexposes no pixel"),
        (-0.1, "got -0.1, which overexposes no pixel"),
        (np.nan, "got NaN (not a number)"),
    ],
)
def test_exposure_fraction_outside_open_interval_is_explained(
    overexposed: float, fragment: str
) -> None:
    """It was 'overexposed must be in (0, 1), got 1.0': no reason, nothing to do."""
    with pytest.raises(InvalidInputError) as caught:
        exposure_gain(np.ones((4, 4)), overexposed)
    message = caught.value.message
    assert fragment in message
    assert "strictly between 0 and 1" in message and "or the gain instead" in message


def test_exposure_of_a_black_scene_says_so() -> None:
    with pytest.raises(InvalidInputError, match="the scene is black"):
        simulate(np.zeros((4, 4)), SensorParams(), overexposed=0.1)


@pytest.mark.parametrize("overexposed", [0.999, 0.9999])
def test_overexposing_more_pixels_than_are_not_black_gives_the_largest_fraction(
    overexposed: float,
) -> None:
    """At 0.999 with 1.8% black pixels it said 'the brightest 100% of pixels have zero
    luminance' (the fraction rounded to a whole percent, and the black ones called the
    brightest). It names the black pixels and the largest fraction that works."""
    scene = np.linspace(0.5, 2.0, 10_000).reshape(100, 100)
    scene.flat[::57] = 0.0  # 176 black pixels: 1.76%
    with pytest.raises(InvalidInputError) as caught:
        simulate(scene, SensorParams(), overexposed=overexposed)
    message = caught.value.message
    assert f"overexposed {overexposed:g} asks for all but the darkest" in message
    assert "176 of 10000 pixels (1.76%) have zero luminance" in message
    assert "give overexposed at most 0.982" in message
    frame = simulate(scene, SensorParams(), overexposed=0.982)
    assert np.isfinite(frame.params.gain) and np.mean(frame.irradiance >= 1.0) >= 0.982


@pytest.mark.parametrize("shape", [(1, 1), (16, 16), (16, 16, 3)])
def test_exposure_of_a_uniform_scene_is_refused(shape: tuple[int, ...]) -> None:
    """Every pixel at the exposure level reached x >= 1: overexposed 0.5 gave a frame of
    W = 1 everywhere (all codes 0), which every decoder reads as W = 0 without a word."""
    with pytest.raises(InvalidInputError) as caught:
        simulate(np.full(shape, 3.0), SensorParams(), overexposed=0.5)
    message = caught.value.message
    assert "every pixel of the scene has the luminance 3" in message
    assert "give the gain instead (below 0.3333" in message


def test_exposure_at_a_darkest_level_most_pixels_share_is_refused() -> None:
    """75% of the pixels share the darkest luminance: overexposed 0.5 brought all of them,
    and so every pixel, to x >= 1. The refusal gives the largest fraction that works."""
    scene = np.full((32, 32), 2.0)
    scene[:8] = np.linspace(3.0, 50.0, 256).reshape(8, 32)
    with pytest.raises(InvalidInputError) as caught:
        simulate(scene, SensorParams(), overexposed=0.5)
    message = caught.value.message
    assert "768 of 1024 pixels (75%) share" in message
    assert "give overexposed at most 0.25" in message
    frame = simulate(scene, SensorParams(), overexposed=0.25)
    assert not frame.winding[8:].any()


@pytest.mark.parametrize("overexposed", [0.5, 0.99, 0.999, 0.999999])
def test_fractions_near_1_give_finite_frames(overexposed: float) -> None:
    scene = np.geomspace(1e-6, 1e6, 4096).reshape(64, 64)
    for encoding in ("mantissa", "modulo", "clip"):
        frame = simulate(scene, SensorParams(encoding=encoding), overexposed=overexposed)
        assert np.isfinite(frame.params.gain) and np.all(np.isfinite(frame.irradiance))
        assert np.mean(frame.irradiance >= 1.0) >= overexposed - 1 / scene.size


def test_an_exposure_level_whose_gain_overflows_is_refused_by_name() -> None:
    """A subnormal exposure level made the gain inf, then 'pixels of the exposed
    irradiance are NaN' (0 x inf)."""
    scene = np.full((4, 4), 1e-310)
    scene[0, 0] = 0.0
    with pytest.raises(InvalidInputError, match=r"gain \(1 / luminance\) overflows float64"):
        simulate(scene, SensorParams(), overexposed=0.5)


def test_gain_and_overexposed_together_are_rejected() -> None:
    with pytest.raises(InvalidInputError, match="either gain or overexposed"):
        simulate(np.ones((4, 4)), SensorParams(gain=2.0), overexposed=0.1)


def test_gray_converts_rgb_to_luminance_before_encoding() -> None:
    scene = np.random.default_rng(0).random((3, 4, 3)) * 5
    frame = simulate(scene, SensorParams(encoding="modulo", gain=1.0), gray=True)
    assert frame.codes.shape == (3, 4)
    assert np.array_equal(frame.irradiance, luminance(scene))


def _noisy_params(seed: int | None) -> SensorParams:
    return SensorParams(encoding="modulo", bits=12, read_noise=0.05, full_well=500.0, seed=seed)


def test_noise_is_seeded_and_reproducible() -> None:
    x = np.linspace(0.0, 6.0, 4096).reshape(64, 64)
    first, again = encode(x, _noisy_params(7)), encode(x, _noisy_params(7))
    assert np.array_equal(first.codes, again.codes)
    assert np.array_equal(first.winding, again.winding)
    other = encode(x, _noisy_params(8))
    assert not np.array_equal(first.codes, other.codes)


def test_read_noise_has_the_requested_sigma_and_wraps() -> None:
    params = SensorParams(encoding="modulo", bits=16, read_noise=0.1, seed=3)
    x = np.full((128, 128), 5.0)
    frame = encode(x, params)
    u_noisy = frame.winding + dequantize(frame.codes, params.bits)
    assert set(np.unique(frame.winding)) <= {4, 5}
    assert abs(np.mean(u_noisy - x)) < 0.005
    assert np.std(u_noisy - x) == pytest.approx(0.1, rel=0.05)


def test_shot_noise_variance_is_x_over_full_well() -> None:
    params = SensorParams(encoding="modulo", bits=16, full_well=400.0, seed=5)
    frame = encode(np.full((128, 128), 2.0), params)
    u_noisy = frame.winding + dequantize(frame.codes, params.bits)
    assert np.var(u_noisy) == pytest.approx(2.0 / 400.0, rel=0.05)


@pytest.mark.parametrize("seed", range(6))
def test_shot_noise_on_a_count_past_float64_keeps_the_pixel(seed: int) -> None:
    """x * full_well overflowed to inf, and inf + sqrt(inf) z was NaN: W came out as
    the int64 minimum (or the pixel inf) for half the seeds."""
    params = SensorParams(encoding="mantissa", full_well=2e4, seed=seed)
    frame = encode(np.array([[1e300, 1e305]]), params)
    assert frame.winding.tolist() == encode(np.array([[1e300, 1e305]]), params.model_copy(
        update={"full_well": None})).winding.tolist()


@pytest.mark.parametrize("encoding", ["modulo", "mantissa"])
def test_max_winding_bounds_the_windings_shot_noise_makes(encoding: str) -> None:
    """Shot noise is drawn after the max_wraps clip; the bound left it out and decoders
    clipped true windings down (542 of 4096 pixels here)."""
    params = SensorParams(encoding=encoding, max_wraps=15.9, full_well=2000.0, seed=1)
    frame = encode(np.full((64, 64), 15.9), params)
    bound = max_winding(params)
    assert bound is not None and frame.winding.max() <= bound


@pytest.mark.parametrize(
    ("encoding", "x"), [("modulo", 2.0), ("mantissa", 0.5), ("mantissa", 8.0)]
)
def test_unwrapped_noise_sigma_matches_simulated_noise(encoding: str, x: float) -> None:
    params = SensorParams(encoding=encoding, bits=16, full_well=400.0, read_noise=0.01, seed=3)
    frame = encode(np.full((128, 128), x), params)
    u_noisy = frame.winding + dequantize(frame.codes, params.bits)
    u = to_unwrapped(np.array(x), params)
    assert float(unwrapped_noise_sigma(u, params)) == pytest.approx(np.std(u_noisy), rel=0.05)


@settings(max_examples=60, deadline=None)
@given(
    encoding=st.sampled_from(["modulo", "mantissa"]),
    read_noise=st.floats(0.0, 0.1),
    full_well=st.one_of(st.none(), st.floats(10.0, 1e6)),
    top=st.floats(0.0, 40.0),
    share=st.floats(0.0, 1.0),
)
def test_largest_noise_sigma_bounds_every_level_up_to_the_top(
    encoding: str, read_noise: float, full_well: float | None, top: float, share: float
) -> None:
    """The bound is at least the noise at any level from 0 to ``top`` (within the grid's
    sampling of a smooth curve), and never less than the read noise."""
    params = SensorParams(encoding=encoding, read_noise=read_noise, full_well=full_well)
    bound = largest_noise_sigma(top, params)
    assert bound >= read_noise
    assert float(unwrapped_noise_sigma(np.array(share * top), params)) <= bound * 1.02 + 1e-12


@pytest.mark.filterwarnings("error")
def test_unwrapped_noise_sigma_near_float64s_top_is_finite_without_warnings() -> None:
    """x * ln(alpha) passed float64 for x near its top (numpy's overflow warning in the
    log); the shot noise there is about 1e-155 wraps, the read noise alone remains."""
    params = SensorParams(encoding="mantissa", alpha=1e6, full_well=100.0, read_noise=0.01)
    top = float(np.log(np.finfo(np.float64).max) / np.log(1e6))  # u of x near 1.8e308
    sigma = unwrapped_noise_sigma(np.array([52.3, top]), params)
    np.testing.assert_allclose(sigma, 0.01)


def test_unwrapped_noise_sigma_without_full_well_is_the_read_noise() -> None:
    params = SensorParams(read_noise=0.02)
    np.testing.assert_array_equal(unwrapped_noise_sigma(np.array([0.0, 3.0]), params), 0.02)


@pytest.mark.parametrize(("encoding", "top"), [("modulo", 16), ("mantissa", 5)])
def test_max_wraps_clips_x_and_bounds_w(encoding: str, top: int) -> None:
    params = SensorParams(encoding=encoding, alpha=2.0, max_wraps=16.0)
    frame = encode(np.array([0.5, 3.0, 16.0, 1e3, 1e9]), params)
    assert frame.irradiance.max() == 16.0
    assert frame.winding.max() == top
    assert max_winding(params) == top


@pytest.mark.parametrize("max_wraps", [2.0**63, 1e19, 1e300])
@pytest.mark.parametrize("decoder", ["herraez+puma", "auto-best"])
def test_a_max_wraps_past_int64_winding_numbers_bounds_no_decoding(
    max_wraps: float, decoder: str
) -> None:
    """A modulo max_wraps of 2^63 or more made the bound a Python int past int64: the
    guided graph cuts (``+puma``, auto at best) and temporal decoding raised
    OverflowError on it, a job's internal error. No frame wraps that often (encode
    refuses W past MAX_WINDING / 2), so it bounds nothing."""
    params = SensorParams(encoding="modulo", max_wraps=max_wraps)
    assert max_winding(params) is None
    frame = encode(np.linspace(0.1, 6.0, 32 * 32).reshape(32, 32), params)
    result = get_decoder(decoder).decode(frame.codes, params)
    np.testing.assert_array_equal(result.winding, frame.winding)


@PROPERTY
@given(x=x_arrays, bits=bits_st)
def test_clip_encoding_stores_min_x_1_with_w_zero(x: np.ndarray, bits: int) -> None:
    params = SensorParams(encoding="clip", bits=bits)
    frame = encode(x, params)
    assert np.all(frame.winding == 0)
    assert np.array_equal(frame.codes, quantize(np.minimum(x, 1.0), bits))
    assert np.all(frame.codes[x >= 1] == 2**bits - 1)
    x_hat = reconstruct(frame.codes, frame.winding, params)
    assert np.all(np.abs(x_hat - np.minimum(x, 1.0)) <= 2.0 ** -(bits + 1))
    assert max_winding(params) == 0


# Hand-computed modulo and mantissa frames at 8 bits: (x, W, code).
MODULO_TABLE = [
    (0.0, 0, 0),
    (0.5, 0, 128),
    (0.999, 0, 255),  # floor(0.999 * 256) = 255
    (1.0, 1, 0),  # the first wrap
    (2.75, 2, 192),
    (16 + 1 / 256, 16, 1),
    (1e6 + 0.5, 1_000_000, 128),
]
MANTISSA_TABLE = [  # alpha = 2: u = x below 1, 1 + log2(x) above
    (0.25, 0, 64),
    (1.0, 1, 0),
    (1.5, 1, 149),  # u = 1.5849625, 0.5849625 * 256 = 149.75
    (3.0, 2, 149),  # u = 2.5849625
    (1024.0, 11, 0),
    (1e6, 20, 238),  # u = 20.9315686, 0.9315686 * 256 = 238.48
]


@pytest.mark.parametrize(
    ("encoding", "table"), [("modulo", MODULO_TABLE), ("mantissa", MANTISSA_TABLE)]
)
def test_forward_model_matches_hand_computed_table(encoding: str, table: list) -> None:
    x, winding, codes = (np.array(column) for column in zip(*table, strict=True))
    frame = encode(x, SensorParams(encoding=encoding, alpha=2.0, bits=8))
    assert np.array_equal(frame.winding, winding)
    assert np.array_equal(frame.codes, codes)


def test_modulo_matches_deepinv_spatial_unwrapping_documented_example() -> None:
    """deepinv's SpatialUnwrapping documents x = [0.5, 1.2, 2.7] -> [0.5, 0.2, -0.3] with
    mode="round" (floor mode gives [0.5, 0.2, 0.7]); our m is the floor-mode value, which
    equals the round-mode value modulo 1."""
    x = np.array([0.5, 1.2, 2.7])
    winding, m = split_unwrapped(to_unwrapped(x, SensorParams(encoding="modulo")), SensorParams())
    assert np.allclose(m, [0.5, 0.2, 0.7])
    assert np.allclose(np.mod([0.5, 0.2, -0.3], 1.0), m)
    assert np.array_equal(winding, [0, 1, 2])


def test_sensor_params_parse_gives_readable_errors() -> None:
    with pytest.raises(InvalidInputError, match="alpha: Input should be greater than 1"):
        SensorParams.parse({"alpha": 0.5})
    with pytest.raises(InvalidInputError, match="bits"):
        SensorParams.parse({"bits": 17})
    assert SensorParams.parse({"encoding": "modulo", "bits": 12}).levels == 4096


@pytest.mark.parametrize(
    ("field", "value", "why"),
    [
        ("max_wraps", 1e-300, "at least 1 wrap .* never wraps and every W would be 0"),
        ("max_wraps", 0.999, "at least 1 wrap .*encoding clip"),
        ("full_well", 1e-300, "at least 1 electron .*no charge to count"),
        ("full_well", 0.5, "at least 1 electron .*unset for no shot noise"),
    ],
)
def test_parameters_below_their_physical_minimum_are_refused_saying_why(
    field: str, value: float, why: str
) -> None:
    """max_wraps 1e-300 clipped every pixel to W = 0 (an all-zero W map from any frame, an
    all-zero simulated frame); full_well 1e-300 counted no electron anywhere."""
    with pytest.raises(InvalidInputError, match=f"{field}: must be {why}"):
        SensorParams.parse({field: value})
    assert getattr(SensorParams.parse({field: 1.0}), field) == 1.0


def test_a_simulated_frame_of_a_lit_scene_under_one_code_step_is_refused() -> None:
    """gain 1e-300 made every code 0 and the frame said nothing of the scene; the error
    gives the gain that lifts the brightest pixel to one code step."""
    frame = simulate(np.array([[0.0, 2.0], [1.0, 4.0]]), SensorParams(bits=8, gain=1e-300))
    with pytest.raises(InvalidInputError, match=r"code 0 .*gain to at least 0\.0009766"):
        check_not_black(frame)
    check_not_black(simulate(np.zeros((2, 2)), SensorParams(gain=1e-300)))  # black is black
    check_not_black(simulate(np.full((2, 2), 1 / 256), SensorParams(bits=8, gain=1.0)))


@pytest.mark.parametrize("encoding", ["modulo", "mantissa"])
def test_a_simulated_frame_of_pixels_just_past_a_wrap_is_refused(encoding: str) -> None:
    """overexposed 0.001 on 16 equal bright pixels (the rest black) put them exactly at
    x = 1, where they store m = 0: every code was 0 and the frame said nothing of the
    scene, yet it was written, since only a frame whose W was 0 everywhere too was
    refused. The error gives the gain that lifts them a code step past the wrap."""
    scene = np.zeros((64, 64))
    scene[:4, :4] = 1e30
    frame = simulate(scene, SensorParams(encoding=encoding, bits=8), overexposed=0.001)
    assert not frame.codes.any() and frame.winding.any()
    message = r"code 0 \(16 pixels lie just past a wrap.* gain to at least 1\.00[0-9]*e-30"
    with pytest.raises(InvalidInputError, match=message):
        check_not_black(frame)


@pytest.mark.parametrize(("encoding", "top", "wraps"), [("modulo", 3, 3), ("mantissa", 16, 5)])
def test_a_frame_clipped_everywhere_at_a_whole_wrap_says_to_lower_the_gain(
    encoding: str, top: float, wraps: int
) -> None:
    """Every lit pixel clipped at a max_wraps whose u is a whole number of wraps stores
    code 0: the error said "raise the gain", which clips them all the same."""
    frame = simulate(np.ones((4, 4)), SensorParams(encoding=encoding, gain=1e50, max_wraps=top))
    assert not frame.codes.any()
    message = (
        f"all 16 lit pixels are clipped at max_wraps = {top:g} wrap units .* stored as "
        f"{wraps} whole wraps, code 0 like black; lower the gain"
    )
    with pytest.raises(InvalidInputError, match=message):
        check_not_black(frame)


@pytest.mark.parametrize(
    ("params", "dtype", "error"),
    [
        (SensorParams(encoding="mantissa", gain=1e-320), np.float32, OutputOverflowError),
        (SensorParams(encoding="modulo", gain=1e-8), np.float16, OutputOverflowError),
        (SensorParams(encoding="modulo", gain=1e308), np.float32, OutputUnderflowError),
        (SensorParams(encoding="mantissa", gain=1e308, max_wraps=16), np.float32,
         OutputUnderflowError),
        (SensorParams(encoding="clip", gain=1e30), np.float16, OutputUnderflowError),
    ],
)  # fmt: skip
def test_a_reconstruction_certain_to_fail_is_refused_before_decoding(
    params: SensorParams, dtype: type[np.floating], error: type[Exception]
) -> None:
    """gain 1e-320 or 1e308 was queued and failed in the worker: x / gain exceeds the
    output type at W = 0, or is lost as 0 at the largest W the parameters allow."""
    codes = np.array([[0, 3], [128, 255]], np.uint8)
    with pytest.raises(error, match="^whatever winding numbers a decoder finds, 4 "):
        check_decodable(codes, params, dtype, scene_referred=True)
    check_decodable(codes, params, dtype, scene_referred=False)  # wrap units fit


@PROPERTY
@given(
    encoding=st.sampled_from(["modulo", "mantissa"]),
    max_wraps=st.floats(1.0, 1e308),
    full_well=st.none() | st.floats(1.0, 1e300),
    gain=st.none() | st.floats(1e-300, 1e300),
)
@example(encoding="modulo", max_wraps=2.0**63, full_well=None, gain=None)
def test_any_clip_is_judged_decodable_or_refused_clearly(
    encoding: str, max_wraps: float, full_well: float | None, gain: float | None
) -> None:
    """A modulo max_wraps of 2^63 or more bounds W past int64: the check built its
    largest-W map with ``np.full(..., W, np.int64)`` and raised OverflowError, a 500 at
    POST /v1/reconstructions and a traceback from mcam reconstruct."""
    params = SensorParams(encoding=encoding, max_wraps=max_wraps, full_well=full_well, gain=gain)
    codes = np.array([[0, 3], [128, 255]], np.uint8)
    with contextlib.suppress(OutputOverflowError, OutputUnderflowError):
        check_decodable(codes, params, np.float32, scene_referred=True)


@pytest.mark.parametrize(
    "params",
    [
        SensorParams(encoding="mantissa", gain=1e-30),  # x / gain fits float32 at W = 0
        SensorParams(encoding="mantissa", gain=1e308),  # fits at W ~ 1000 (no max_wraps)
        SensorParams(encoding="modulo", gain=1e20),  # fits at W ~ 1e15
    ],
)
def test_a_reconstruction_that_some_winding_numbers_store_is_left_to_the_decoder(
    params: SensorParams,
) -> None:
    codes = np.array([[0, 3], [128, 255]], np.uint8)
    check_decodable(codes, params, np.float32, scene_referred=True)


@pytest.mark.filterwarnings("error")
def test_an_exposure_past_float64_is_refused_without_a_numpy_warning() -> None:
    with pytest.raises(OutputOverflowError, match="exposed irradiance exceed the float64"):
        simulate(np.full((2, 2), 10.0), SensorParams(gain=1e308))


def test_half_float_underflow_also_names_a_wrong_scene_gain() -> None:
    codes, winding = np.array([[3]], np.uint8), np.zeros((1, 1), np.int64)
    huge_gain = SensorParams(encoding="modulo", gain=1e300)
    with pytest.raises(OutputUnderflowError, match="float32 .* as 0 too: .*gain 1e\\+300"):
        reconstruct(codes, winding, huge_gain, np.float16, scene_referred=True)
    with pytest.raises(OutputUnderflowError, match="ask for float32 .*, or .*gain 1e\\+09"):
        reconstruct(codes, winding, huge_gain.model_copy(update={"gain": 1e9}), np.float16,
                    scene_referred=True)  # fmt: skip


@pytest.mark.filterwarnings("error")
def test_a_scene_referred_overflow_gives_no_numpy_warning() -> None:
    assert to_scene(np.array([1e300]), 1e-300)[0] == np.inf


def test_parameter_differences_leave_out_the_noise_seed() -> None:
    base = SensorParams(encoding="mantissa", seed=1)
    assert base.differences(base.model_copy(update={"seed": 2})) == []
    assert base.differences(SensorParams(encoding="modulo", bits=10, seed=1)) == [
        "encoding",
        "bits",
    ]
