"""Tests of models/training/data.py: seeded on-the-fly training pairs."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from models.formation import SensorParams, to_unwrapped
from models.training.data import PairConfig, psnr_weights, sample_batch
from models.training.networks import NUM_CLASSES


@pytest.mark.parametrize("encoding", ["mantissa", "modulo"])
def test_batches_have_shapes_ranges_and_wraps(encoding: str) -> None:
    m, winding = sample_batch(3, 0, PairConfig(encoding, crop=32, batch=4))
    assert m.shape == winding.shape == (4, 1, 32, 32)
    assert m.dtype == np.float32 and winding.dtype == np.int64
    assert m.min() > 0 and m.max() < 1
    assert winding.min() == 0 and winding.max() < NUM_CLASSES
    assert 0.02 < (winding > 0).mean() < 0.5


def test_batches_depend_only_on_seed_and_step() -> None:
    config = PairConfig("mantissa", crop=32, batch=2, max_read_noise=0.02)
    a = sample_batch(5, 7, config)
    b = sample_batch(5, 7, config)
    c = sample_batch(5, 8, config)
    np.testing.assert_array_equal(a[0], b[0])
    np.testing.assert_array_equal(a[1], b[1])
    assert not np.array_equal(a[0], c[0])


def test_mantissa_training_winding_stays_below_the_class_count() -> None:
    params = SensorParams(encoding="mantissa")
    assert float(to_unwrapped(np.array(2.0**12), params)) < NUM_CLASSES


def test_crops_as_tall_as_the_panoramas_come_from_them_at_full_scale() -> None:
    # The training panoramas are 256 px tall: a 256 px crop has no room for the 2x
    # downscale, so every real-scene crop of that size is taken at 1x.
    config = PairConfig("mantissa", crop=256, batch=4, synthetic_fraction=0.0)
    m, winding = sample_batch(0, 0, config)
    assert m.shape == winding.shape == (4, 1, 256, 256)


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**31), crops=st.integers(1, 3), size=st.integers(1, 9))
def test_psnr_weights_have_mean_one_per_crop_and_grow_with_w(
    seed: int, crops: int, size: int
) -> None:
    rng = np.random.default_rng(seed)
    m = rng.uniform(0.0, 1.0, (crops, 1, size, size)).astype(np.float32)
    winding = rng.integers(0, NUM_CLASSES, (crops, 1, size, size))
    weights = psnr_weights(m, winding, "mantissa")
    assert weights.shape == m.shape and weights.dtype == np.float32
    assert np.all(np.isfinite(weights)) and np.all(weights > 0)
    np.testing.assert_allclose(weights.mean(axis=(1, 2, 3)), 1.0, rtol=1e-5)
    u = winding + m.astype(np.float64)
    order = np.argsort(u[0].ravel())
    assert np.all(np.diff(weights[0].ravel()[order]) >= -1e-5)


def test_psnr_weights_follow_the_irradiance_step_of_one_wrap() -> None:
    # Mantissa at alpha 2: one wrap more at u = 3.5 (x = 2^2.5) costs x; at u = 0.5
    # it costs 2^0.5 - 0.5. Modulo: every wrong wrap costs 1, so the weights are flat.
    m = np.full((1, 1, 1, 2), 0.5, np.float32)
    winding = np.array([0, 3]).reshape(1, 1, 1, 2)
    weights = psnr_weights(m, winding, "mantissa")[0, 0, 0]
    assert weights[1] / weights[0] == pytest.approx((2**2.5 / (2**0.5 - 0.5)) ** 2, rel=1e-5)
    np.testing.assert_array_equal(psnr_weights(m, winding, "modulo"), 1.0)
