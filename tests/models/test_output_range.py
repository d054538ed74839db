"""models/output_range.py: values checked against the float type they are stored in."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import example, given
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


#: Half the smallest float32 subnormal: a float64 value there rounds (to even) to 0.
HALF_TINY_32 = float(np.finfo(np.float32).smallest_subnormal) / 2


def test_a_float64_value_that_rounds_to_zero_in_float32_is_refused_and_one_above_kept() -> None:
    assert np.float32(HALF_TINY_32) == 0 and np.float32(np.nextafter(HALF_TINY_32, 1)) != 0
    for value in (HALF_TINY_32, -HALF_TINY_32, np.nextafter(HALF_TINY_32, 0)):
        with pytest.raises(OutputUnderflowError, match="1 nonzero pixels"):
            ensure_nonzero_kept(np.array([1.0, value]), np.float32, "frame")
    ensure_nonzero_kept(np.array([np.nextafter(HALF_TINY_32, 1), 0.0]), np.float32, "frame")


@given(st.floats(min_value=-4, max_value=4), st.sampled_from([np.float32, np.float16]))
@example(factor=1.0, dtype=np.float16)  # the tie: rounds to even, 0
def test_refused_exactly_when_the_cast_would_turn_a_nonzero_value_into_zero(
    factor: float, dtype: type[np.floating]
) -> None:
    """numpy's own cast is the oracle: a float64 value (``factor`` times half the smallest
    subnormal of ``dtype``, so around the edge) is refused iff it is nonzero and stored
    as 0 in ``dtype``."""
    value = factor * float(np.finfo(dtype).smallest_subnormal) / 2
    lost = value != 0 and np.array([value]).astype(dtype)[0] == 0
    try:
        ensure_nonzero_kept(np.array([value]), dtype, "frame")
    except OutputUnderflowError:
        assert lost, f"{value!r} is kept as {dtype.__name__} but was refused"
    else:
        assert not lost, f"{value!r} becomes 0 as {dtype.__name__} but was not refused"


def test_remedies_point_the_right_way_for_scene_referred_output() -> None:
    """x / gain overflows when the gain is tiny (raise it) and underflows when it is
    huge (lower it); wrap units overflow with too many wraps."""
    assert "a higher gain gives smaller values" in overflow_remedy(np.float32, 1e-40)
    assert "lower the gain for larger values" in underflow_remedy(np.float32, 1e40)
    assert "lower the gain or alpha" in overflow_remedy(np.float32)
    assert overflow_remedy(np.float16).startswith("ask for float32")
    assert "check the winding numbers" in underflow_remedy(np.float64)


def test_half_floats_are_told_to_use_float32_only_where_float32_holds_the_values() -> None:
    """Values past float32 as well (x / gain at gain 1e-300) were told "ask for float32
    output instead of half floats", which fails the same way."""
    with pytest.raises(OutputOverflowError, match="ask for float32 output instead"):
        ensure_fits(np.array([1e5]), np.float16, "frame", 1e-4)
    with pytest.raises(OutputOverflowError) as huge:
        ensure_fits(np.array([1e5, 1e300]), np.float16, "frame", 1e-300)
    assert "float32 output cannot hold them either: " in huge.value.message
    assert "instead of half floats" not in huge.value.message
    with pytest.raises(OutputUnderflowError, match="ask for float32 output instead"):
        ensure_nonzero_kept(np.array([1e-9]), np.float16, "frame", 1e9)
    with pytest.raises(OutputUnderflowError) as tiny:
        ensure_nonzero_kept(np.array([1e-9, 1e-300]), np.float16, "frame", 1e300)
    assert "float32 output would store them as 0 too: " in tiny.value.message
    assert "instead of half floats" not in tiny.value.message
