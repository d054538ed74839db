"""Tests of models/training/data.py: seeded on-the-fly training pairs."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from models.formation import SensorParams, to_unwrapped
from models.training.data import PairConfig, batch_stream, class_errors, sample_batch
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
@given(
    seed=st.integers(0, 2**31), crops=st.integers(1, 3), size=st.integers(1, 9),
    encoding=st.sampled_from(["mantissa", "modulo"]),
)  # fmt: skip
def test_class_errors_vanish_at_the_true_w_and_grow_away_from_it(
    seed: int, crops: int, size: int, encoding: str
) -> None:
    rng = np.random.default_rng(seed)
    m = rng.uniform(0.0, 1.0, (crops, 1, size, size)).astype(np.float32)
    winding = rng.integers(0, NUM_CLASSES, (crops, 1, size, size))
    errors = class_errors(m, winding, encoding)
    assert errors.shape == (crops, NUM_CLASSES, size, size) and errors.dtype == np.float32
    assert np.all(np.isfinite(errors)) and np.all(errors >= 0)
    np.testing.assert_array_equal(np.take_along_axis(errors, winding, axis=1), 0.0)
    below = np.arange(NUM_CLASSES).reshape(1, -1, 1, 1) < winding
    steps = np.diff(errors, axis=1)
    assert np.all(steps[below[:, :-1]] <= 0) and np.all(steps[~below[:, :-1]] >= 0)


def test_class_errors_are_relative_squared_irradiance_errors() -> None:
    # Mantissa at alpha 2, true W = 3 at m = 0.5 (x = 2^2.5, the crop's peak): W = 4
    # answers twice the truth, W = 2 half of it; modulo errors are (k - W)^2 / peak^2.
    m = np.full((1, 1, 1, 1), 0.5, np.float32)
    winding = np.full((1, 1, 1, 1), 3)
    mantissa = class_errors(m, winding, "mantissa")[0, :, 0, 0]
    assert mantissa[4] == pytest.approx(1.0) and mantissa[2] == pytest.approx(0.25)
    modulo = class_errors(m, winding, "modulo")[0, :, 0, 0]
    assert modulo[5] == pytest.approx(4 / 3.5**2)


def test_prefetched_stream_equals_the_in_process_one() -> None:
    small, large = PairConfig("mantissa", crop=32, batch=2), PairConfig("mantissa", 64, 1)
    plan = [(0, small), (1, small), (2, large), (3, large), (4, small)]
    alone = list(batch_stream(4, plan, with_errors=True, workers=0))
    ahead = list(batch_stream(4, plan, with_errors=True, workers=2))
    assert [b.m.shape for b in ahead] == [b.m.shape for b in alone]
    for a, b in zip(alone, ahead, strict=True):
        np.testing.assert_array_equal(a.m, b.m)
        np.testing.assert_array_equal(a.winding, b.winding)
        assert a.errors is not None and b.errors is not None
        np.testing.assert_array_equal(a.errors, b.errors)


def test_stream_without_errors_leaves_them_out() -> None:
    (batch,) = batch_stream(0, [(0, PairConfig("modulo", 32, 1))], with_errors=False)
    assert batch.errors is None and batch.m.shape == (1, 1, 32, 32)


def test_colour_crops_give_one_channel_of_a_frame_exposed_on_luminance() -> None:
    """With colour_fraction 1 every HDRI pair is one channel of a colour frame: channels
    wrap apart from the luminance a grayscale crop shows, and the pairs stay 2-D."""
    colour = PairConfig("mantissa", crop=32, batch=6, synthetic_fraction=0.0, colour_fraction=1.0)
    gray = PairConfig("mantissa", crop=32, batch=6, synthetic_fraction=0.0)
    m, winding = sample_batch(11, 0, colour)
    assert m.shape == winding.shape == (6, 1, 32, 32)
    assert winding.min() == 0 and winding.max() < NUM_CLASSES
    assert not np.array_equal(m, sample_batch(11, 0, gray)[0])
    np.testing.assert_array_equal(m, sample_batch(11, 0, colour)[0])


def test_glow_fraction_0_keeps_the_earlier_data_and_1_adds_lobes() -> None:
    """Recipes without lobes see the data they were trained on; with glow_fraction 1
    every synthetic scene gets its lobes: the same scene, brighter, with more high W."""
    plain = PairConfig("mantissa", crop=32, batch=6, synthetic_fraction=1.0)
    zero = PairConfig("mantissa", crop=32, batch=6, synthetic_fraction=1.0, glow_fraction=0.0)
    lit = PairConfig("mantissa", crop=32, batch=6, synthetic_fraction=1.0, glow_fraction=1.0)
    m, winding = sample_batch(4, 0, plain)
    np.testing.assert_array_equal(m, sample_batch(4, 0, zero)[0])
    lit_m, lit_winding = sample_batch(4, 0, lit)
    assert lit_m.shape == m.shape and lit_winding.max() < NUM_CLASSES
    assert not np.array_equal(lit_m, m)
    np.testing.assert_array_equal(lit_m, sample_batch(4, 0, lit)[0])
