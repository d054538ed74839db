"""Metrics (models/metrics.py): each against a hand-computed or independently known value."""

from __future__ import annotations

import importlib.util
import math
from collections.abc import Callable

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays
from skimage.metrics import structural_similarity

from models.errors import InvalidInputError
from models.metrics import (
    MS_SSIM_WEIGHTS,
    PSNR_CAP,
    capped_psnr,
    evaluate,
    flip_inputs,
    hdr_flip,
    ms_ssim,
    ms_ssim_ldr,
    ms_ssim_scales,
    psnr,
    pu21_psnr,
    reinhard,
    ssim,
    ssim_ldr,
    winding_accuracy,
)

HAS_FLIP = importlib.util.find_spec("flip_evaluator") is not None
C1 = 0.01**2  # SSIM constants for data range 1


@pytest.fixture(scope="module")
def hdr_pair() -> tuple[np.ndarray, np.ndarray]:
    """A 64 x 64 HDR reference (4 decades) and a 2 %-noisy estimate of it."""
    rng = np.random.default_rng(11)
    reference = np.exp(rng.uniform(0, np.log(1e4), (64, 64)))
    estimate = reference * (1 + 0.02 * rng.standard_normal(reference.shape))
    return estimate, reference


def _noisy(image: np.ndarray, sigma: float, seed: int = 0) -> np.ndarray:
    noise = np.random.default_rng(seed).standard_normal(image.shape)
    return np.clip(image + sigma * noise, 0.0, 1.0)


def _texture(shape: tuple[int, int]) -> np.ndarray:
    yy, xx = np.mgrid[: shape[0], : shape[1]]
    return 0.5 + 0.4 * np.sin(xx / 3.0) * np.cos(yy / 5.0)


def test_winding_accuracy_counts_exact_matches() -> None:
    assert winding_accuracy(np.array([[0, 1], [2, 3]]), np.array([[0, 1], [2, 4]])) == 0.75
    assert winding_accuracy(np.zeros((3, 3), np.int64), np.zeros((3, 3), np.uint8)) == 1.0


@pytest.mark.parametrize(
    ("w", "w_ref", "message"),
    [
        (np.zeros((2, 2), int), np.zeros((2, 3), int), "does not match"),
        (np.zeros((0,), int), np.zeros((0,), int), "empty"),
        (np.zeros((2, 2)), np.zeros((2, 2), int), "integers"),
    ],
)
def test_winding_accuracy_rejects_bad_maps(w: np.ndarray, w_ref: np.ndarray, message: str) -> None:
    with pytest.raises(InvalidInputError, match=message):
        winding_accuracy(w, w_ref)


def test_psnr_hand_computed() -> None:
    reference = np.array([[0.0, 4.0], [2.0, 4.0]])
    estimate = reference + np.array([[1.0, 0.0], [0.0, -1.0]])
    # peak 4, mse (1 + 1) / 4 = 0.5: 10 log10(16 / 0.5) = 10 log10(32)
    assert psnr(estimate, reference) == pytest.approx(10 * math.log10(32.0), rel=1e-12)
    assert psnr(estimate * 1e-9, reference * 1e-9) == pytest.approx(10 * math.log10(32.0))


def test_psnr_of_identical_images_is_infinite() -> None:
    image = np.random.default_rng(1).random((8, 8))
    assert psnr(image, image) == float("inf")
    assert pu21_psnr(image, image) == float("inf")


def test_pu21_psnr_hand_computed() -> None:
    """Reference max 4000 maps to 4000 cd/m^2 (scale 1); one of two pixels differs."""
    reference = np.array([[100.0, 4000.0]])
    estimate = np.array([[10.0, 4000.0]])
    # PU21(100) - PU21(10) from the reference encoder (see test_pu21.py); peak PU21(10000).
    difference = 256.3838973127039 - 123.64748355384738
    expected = 20 * math.log10(595.393920020095) - 10 * math.log10(difference**2 / 2)
    assert pu21_psnr(estimate, reference) == pytest.approx(expected, rel=1e-9)
    assert pu21_psnr(estimate / 40.0, reference / 40.0) == pytest.approx(expected, rel=1e-9)


def test_pu21_psnr_ranks_dark_errors_worse_than_linear_psnr_does(hdr_pair) -> None:
    """+50 % on the darkest fifth is invisible to linear PSNR (peak-dominated), not to PU21."""
    noisy, reference = hdr_pair
    dark_error = reference.copy()
    dark_error[reference < np.quantile(reference, 0.2)] *= 1.5
    assert psnr(dark_error, reference) > psnr(noisy, reference)
    assert pu21_psnr(dark_error, reference) < pu21_psnr(noisy, reference)


def test_reinhard_maps_the_log_average_to_the_key() -> None:
    reference = np.full((4, 4), 7.0)
    tonemapped = reinhard(reference, reference)
    assert tonemapped == pytest.approx(np.full((4, 4), 0.18 / 1.18), rel=1e-5)
    brighter = reinhard(reference * 2, reference)
    assert brighter == pytest.approx(np.full((4, 4), 0.36 / 1.36), rel=1e-5)


def test_reinhard_uses_luminance_of_rgb() -> None:
    rgb = np.zeros((2, 2, 3))
    rgb[..., 1] = 3.0
    gray = np.full((2, 2), 3.0 * 0.7152)
    assert np.allclose(reinhard(rgb, rgb), reinhard(gray, gray))


def test_reinhard_of_a_pixel_past_float64_times_the_key_is_white() -> None:
    """0.18 * 1e305 / 1e-5 is past float64: inf / inf made the pixel NaN."""
    reference = np.full((2, 2), 1e-5)
    image = np.array([[1e305, 1e-5], [1e-5, 0.0]])
    tonemapped = reinhard(image, reference)
    assert tonemapped[0, 0] == 1.0
    assert tonemapped[0, 1] == pytest.approx(0.18 / 1.18, rel=1e-5) and tonemapped[1, 1] == 0.0


def test_ssim_matches_scikit_image() -> None:
    a = _texture((48, 40))
    b = _noisy(a, 0.1)
    expected = structural_similarity(
        a, b, data_range=1.0, gaussian_weights=True, sigma=1.5, use_sample_covariance=False
    )
    assert ssim_ldr(a, b) == pytest.approx(expected, rel=1e-12)


def test_ssim_of_constant_images_is_the_luminance_term() -> None:
    a, b = np.full((16, 16), 0.3), np.full((16, 16), 0.5)
    expected = (2 * 0.3 * 0.5 + C1) / (0.3**2 + 0.5**2 + C1)
    assert ssim_ldr(a, b) == pytest.approx(expected, rel=1e-9)


def test_ms_ssim_of_constant_images_is_the_last_scale_luminance_term() -> None:
    """Constant images have contrast-structure 1 at every scale: MS-SSIM = l ** w_5."""
    a, b = np.full((256, 256), 0.3), np.full((256, 256), 0.5)
    luminance_term = (2 * 0.3 * 0.5 + C1) / (0.3**2 + 0.5**2 + C1)
    assert ms_ssim_ldr(a, b) == pytest.approx(luminance_term ** MS_SSIM_WEIGHTS[-1], rel=1e-9)


def test_ms_ssim_properties() -> None:
    a = _texture((192, 192))
    assert ms_ssim_ldr(a, a) == pytest.approx(1.0)
    scores = [ms_ssim_ldr(a, _noisy(a, sigma)) for sigma in (0.01, 0.05, 0.2)]
    assert 1.0 > scores[0] > scores[1] > scores[2] > 0.0
    b = _noisy(a, 0.05)
    assert ms_ssim_ldr(a, b) == pytest.approx(ms_ssim_ldr(b, a), rel=1e-12)


@pytest.mark.parametrize(("sigma", "expected"), [(0.05, 0.98988556), (0.2, 0.89189771)])
def test_ms_ssim_matches_pytorch_msssim(sigma: float, expected: float) -> None:
    """Values computed once with pytorch-msssim 1.0.0 (float64 tensors, data_range 1)."""
    a = _texture((256, 256))
    assert ms_ssim_ldr(a, _noisy(a, sigma)) == pytest.approx(expected, abs=1e-6)


def test_ms_ssim_uses_as_many_scales_as_fit() -> None:
    assert ms_ssim_scales((256, 256)) == 5
    assert ms_ssim_scales((176, 300)) == 5
    assert ms_ssim_scales((175, 300)) == 4
    assert ms_ssim_scales((21, 21)) == 1
    a = _texture((21, 30))
    b = _noisy(a, 0.1)
    assert ms_ssim_ldr(a, b) == pytest.approx(ssim_ldr(a, b), rel=1e-12)


def test_ssim_needs_the_window_to_fit() -> None:
    with pytest.raises(InvalidInputError, match="at least 11 x 11"):
        ssim_ldr(np.zeros((10, 20)), np.zeros((10, 20)))


def test_hdr_ssims_of_identical_images_are_one(hdr_pair) -> None:
    _, reference = hdr_pair
    assert ssim(reference, reference) == pytest.approx(1.0)
    assert ms_ssim(reference, reference) == pytest.approx(1.0)


def test_hdr_ssims_are_invariant_to_a_common_scale(hdr_pair) -> None:
    estimate, reference = hdr_pair
    assert ssim(estimate * 3, reference * 3) == pytest.approx(ssim(estimate, reference))
    assert ssim(estimate, reference) < 1.0


def test_hdr_flip_value_or_none() -> None:
    reference = np.exp(np.random.default_rng(2).uniform(0, 5, (24, 24)))
    if not HAS_FLIP:
        assert hdr_flip(reference * 2, reference) is None
        return
    assert hdr_flip(reference, reference) == 0.0
    small, large = hdr_flip(reference * 1.1, reference), hdr_flip(reference * 3, reference)
    assert 0.0 < small < large <= 1.0


def test_flip_inputs_put_the_reference_peak_at_one() -> None:
    reference = np.full((4, 4), 1e-30)
    estimate = np.full((4, 4), 1e10)
    x, ref = flip_inputs(estimate, reference)
    assert ref.shape == x.shape == (4, 4, 3) and ref.dtype == x.dtype == np.float32
    assert np.all(ref == 1.0)
    assert np.all(x == np.finfo(np.float32).max)  # 1e40 does not fit: clipped, not inf


@pytest.mark.skipif(not HAS_FLIP, reason="flip-evaluator not installed")
def test_hdr_flip_does_not_depend_on_a_common_scale() -> None:
    reference = np.exp(np.random.default_rng(2).uniform(0, 5, (24, 24)))
    error = hdr_flip(reference * 1.1, reference)
    assert hdr_flip(reference * 1.1e-8, reference * 1e-8) == pytest.approx(error, rel=1e-5)


@pytest.mark.parametrize("metric", [psnr, pu21_psnr, ssim, ms_ssim, evaluate])
@pytest.mark.parametrize(
    ("estimate", "message"),
    [
        (np.ones((16, 15)), "does not match"),
        (np.where(np.eye(16) > 0, np.nan, 1.0), "16 NaN or infinite"),
        (np.where(np.eye(16) > 0, np.inf, 1.0), "16 NaN or infinite"),
        (-np.ones((16, 16)), "256 negative"),
    ],
)
def test_bad_images_are_rejected(metric: Callable, estimate: np.ndarray, message: str) -> None:
    with pytest.raises(InvalidInputError, match=message):
        metric(estimate, np.ones((16, 16)))


def test_all_zero_reference_is_rejected() -> None:
    with pytest.raises(InvalidInputError, match="all zero"):
        psnr(np.ones((4, 4)), np.zeros((4, 4)))


def test_evaluate_returns_every_metric_that_applies(hdr_pair) -> None:
    estimate, reference = hdr_pair
    winding = np.zeros((64, 64), np.int64)
    results = evaluate(estimate, reference, winding, winding, flip=False)
    assert set(results) == {"winding_accuracy", "psnr", "pu21_psnr", "ssim", "ms_ssim"}
    assert results["psnr"] == pytest.approx(psnr(estimate, reference))
    assert results["winding_accuracy"] == 1.0
    tiny = evaluate(estimate[:8, :8], reference[:8, :8], flip=False)
    assert set(tiny) == {"psnr", "pu21_psnr"}


def test_evaluate_includes_hdr_flip_when_installed() -> None:
    reference = np.exp(np.random.default_rng(3).uniform(0, 5, (16, 16, 3)))
    assert ("hdr_flip" in evaluate(reference * 1.2, reference)) == HAS_FLIP


def test_evaluate_accepts_single_channel_stacks() -> None:
    reference = np.exp(np.random.default_rng(4).uniform(0, 5, (16, 16)))
    stacked = evaluate(reference[:, :, None] * 1.1, reference[:, :, None], flip=False)
    assert stacked == evaluate(reference * 1.1, reference, flip=False)


def test_evaluate_needs_both_winding_maps() -> None:
    with pytest.raises(InvalidInputError, match="needs both"):
        evaluate(np.ones((4, 4)), np.ones((4, 4)), winding=np.zeros((4, 4), int))


@pytest.mark.parametrize("bad", [np.nan, np.inf, -0.5])
@pytest.mark.parametrize("metric", [ssim_ldr, ms_ssim_ldr])
def test_display_referred_ssim_refuses_values_that_are_not_finite_or_negative(
    metric: Callable[..., float], bad: float
) -> None:
    """They returned NaN for one NaN pixel, and took negative values."""
    a = np.full((32, 32), 0.5)
    b = a.copy()
    b[3, 4] = bad
    with pytest.raises(InvalidInputError, match="finite values >= 0"):
        metric(a, b)


def test_capped_psnr_caps_an_exact_frame_and_refuses_nan() -> None:
    assert capped_psnr(np.inf) == PSNR_CAP and capped_psnr(31.5) == 31.5
    for bad in (np.nan, -np.inf):
        with pytest.raises(InvalidInputError):
            capped_psnr(bad)


@st.composite
def hdr_images(draw: st.DrawFn, min_side: int = 2) -> tuple[np.ndarray, np.ndarray]:
    """A reference spanning up to 6 decades and an estimate equal to it or off it by up
    to 0.1-20 % per pixel (H x W, or H x W x 3), from a drawn seed: cheap to draw at any
    size. (Errors far below 0.1 % give PSNRs above 200 dB, where rounding the scaled
    pixel values moves the figure more than the tests' tolerance.)"""
    rows, cols = draw(st.integers(min_side, 40)), draw(st.integers(min_side, 40))
    shape = (rows, cols, 3) if draw(st.booleans()) else (rows, cols)
    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
    reference = 10.0 ** rng.uniform(-3, draw(st.floats(-2.0, 3.0)), shape)
    error = draw(st.one_of(st.just(0.0), st.floats(1e-3, 0.2)))
    estimate = reference * (1 + error * rng.uniform(-1, 1, shape))
    return estimate, reference


SCALES = st.floats(1e-6, 1e6)


@settings(max_examples=40)
@given(pair=hdr_images(), scale=SCALES)
def test_psnrs_do_not_depend_on_a_common_scale(pair: tuple[np.ndarray, np.ndarray],
                                               scale: float) -> None:
    estimate, reference = pair
    for metric in (psnr, pu21_psnr):
        assert metric(estimate * scale, reference * scale) == pytest.approx(
            metric(estimate, reference), rel=1e-9, abs=1e-9
        )


@settings(max_examples=40)
@given(pair=hdr_images(), scale=SCALES)
def test_identical_images_have_infinite_psnr_and_ssims_of_one(
    pair: tuple[np.ndarray, np.ndarray], scale: float
) -> None:
    _, reference = pair
    image = reference * scale
    assert psnr(image, image) == pu21_psnr(image, image) == math.inf
    assert capped_psnr(psnr(image, image)) == PSNR_CAP
    if min(image.shape[:2]) >= 11:
        assert ssim(image, image) == pytest.approx(1.0)
        assert ms_ssim(image, image) == pytest.approx(1.0)


@settings(max_examples=40)
@given(pair=hdr_images())
def test_psnr_is_symmetric_between_images_of_the_same_peak(
    pair: tuple[np.ndarray, np.ndarray],
) -> None:
    """Squared errors are symmetric; only the peak (the reference's) is not."""
    estimate, reference = pair
    estimate = np.minimum(estimate, reference.max())
    estimate.flat[np.argmax(reference)] = reference.max()
    assert psnr(estimate, reference) == pytest.approx(psnr(reference, estimate), rel=1e-12)


@settings(max_examples=40)
@given(pair=hdr_images())
def test_doubling_every_error_costs_20_log10_2_db_of_psnr(
    pair: tuple[np.ndarray, np.ndarray],
) -> None:
    """The error of an estimate at most 20 % off, doubled, stays non-negative: the MSE
    goes up 4 times, the PSNR down 20 log10(2) = 6.02 dB."""
    estimate, reference = pair
    doubled = reference + 2 * (estimate - reference)
    if np.array_equal(estimate, reference):
        assert psnr(doubled, reference) == math.inf
        return
    drop = psnr(estimate, reference) - psnr(doubled, reference)
    assert drop == pytest.approx(20 * math.log10(2), rel=1e-9)


@settings(max_examples=25)
@given(pair=hdr_images(min_side=11))
def test_ssims_are_symmetric_and_at_most_one(pair: tuple[np.ndarray, np.ndarray]) -> None:
    """On display-referred images (the tonemapped reference and estimate)."""
    estimate, reference = pair
    a, b = reinhard(estimate, reference), reinhard(reference, reference)
    for metric in (ssim_ldr, ms_ssim_ldr):
        forward, backward = metric(a, b), metric(b, a)
        assert forward == pytest.approx(backward, abs=1e-12)
        assert forward <= 1.0 + 1e-12


@settings(max_examples=40)
@given(
    winding=arrays(np.int64, st.tuples(st.integers(1, 8), st.integers(1, 8)),
                   elements=st.integers(0, 5)),
    seed=st.integers(0, 2**32 - 1),
)
def test_winding_accuracy_is_the_share_of_equal_pixels_either_way(
    winding: np.ndarray, seed: int
) -> None:
    other = np.where(np.random.default_rng(seed).random(winding.shape) < 0.5, winding, 9)
    share = winding_accuracy(winding, other)
    assert share == winding_accuracy(other, winding) == np.mean(winding == other)
    assert winding_accuracy(winding, winding) == 1.0
