"""Tests of models/training/data.py: seeded on-the-fly training pairs."""

from __future__ import annotations

import numpy as np
import pytest

from models.formation import SensorParams, to_unwrapped
from models.training.data import PairConfig, sample_batch
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
