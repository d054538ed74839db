"""models/output_range.py: values checked against the float type they are stored in."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from models.errors import InvalidInputError, OutputOverflowError, OutputUnderflowError
from models.output_range import (
    ensure_fits,
    ensure_nonzero_kept,
    overflow_remedy,
    underflow_remedy,
)

FLOAT32_VALUES = st.floats(allow_nan=False, allow_infinity=False, width=32)


@given(arrays(np.float64, st.integers(1, 32), elements=FLOAT32_VALUES))
def test_values_within_float32_fit_it(values: np.ndarray) -> None:
    ensure_fits(values, np.float32, "frame")


def test_overflow_counts_the_pixels_and_names_the_type() -> None:
    values = np.array([1.0, 1e39, -1e39, np.inf])
    with pytest.raises(OutputOverflowError, match="3 pixels of the frame exceed the float32"):
        ensure_fits(values, np.float32, "frame")
    with pytest.raises(OutputOverflowError, match="float16"):
        ensure_fits(np.array([70_000.0]), np.float16, "frame")


def test_nan_is_no_number_at_all() -> None:
    with pytest.raises(InvalidInputError, match="2 pixels of the frame are NaN"):
        ensure_fits(np.array([np.nan, 1.0, np.nan]), np.float32, "frame")


def test_nonzero_values_that_would_be_stored_as_zero_are_refused() -> None:
    with pytest.raises(OutputUnderflowError, match="1 nonzero pixels .* stored as 0"):
        ensure_nonzero_kept(np.array([0.0, 1e-300, 1.0]), np.float32, "frame")
    with pytest.raises(OutputUnderflowError, match="float16"):
        ensure_nonzero_kept(np.array([1e-9]), np.float16, "frame")


@pytest.mark.parametrize("values", [np.zeros(4), np.array([1e-40, 1.0]), np.array([-2e-45])])
def test_zeros_and_storable_subnormals_pass(values: np.ndarray) -> None:
    ensure_nonzero_kept(values, np.float32, "frame")


def test_a_type_no_wider_than_the_target_loses_nothing() -> None:
    ensure_nonzero_kept(np.array([1e-45], np.float32), np.float32, "frame")


def test_remedies_point_the_right_way_for_scene_referred_output() -> None:
    """x / gain overflows when the gain is tiny (raise it) and underflows when it is
    huge (lower it); wrap units overflow with too many wraps."""
    assert "a higher gain gives smaller values" in overflow_remedy(np.float32, 1e-40)
    assert "lower the gain for larger values" in underflow_remedy(np.float32, 1e40)
    assert "lower the gain or alpha" in overflow_remedy(np.float32)
    assert overflow_remedy(np.float16).startswith("ask for float32")
    assert "check the winding numbers" in underflow_remedy(np.float64)
