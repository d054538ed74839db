"""PU21 'banding_glare' encoding (models/pu21.py) against the reference implementation."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from models.errors import InvalidInputError
from models.pu21 import L_MAX, L_MIN, PU21_PEAK, pu21_decode, pu21_encode

# PU21 values of the reference MATLAB encoder (gfxdisp/pu21 pu21_encoder.m, banding_glare),
# evaluated in float64 from its published formula and parameters.
REFERENCE_VALUES = [
    (0.01, 0.3722322097176101),
    (0.1, 5.717073839669447),
    (1.0, 36.54391113941914),
    (10.0, 123.64748355384738),
    (100.0, 256.3838973127039),
    (1000.0, 420.0969213492443),
    (4000.0, 527.4939005367281),
    (10000.0, 595.393920020095),
]


@pytest.mark.parametrize(("luminance", "value"), REFERENCE_VALUES)
def test_encode_matches_reference_values(luminance: float, value: float) -> None:
    assert pu21_encode(luminance) == pytest.approx(value, rel=1e-12)


def test_published_anchor_points() -> None:
    """The reference documents 100 cd/m^2 -> about 256 and an encoded range 0 to ~600."""
    assert pu21_encode(100.0) == pytest.approx(256.0, abs=0.5)
    assert pu21_encode(L_MIN) == pytest.approx(0.0, abs=1e-6)
    assert PU21_PEAK == pytest.approx(595.394, abs=1e-3)


def test_luminance_is_clamped_to_the_encoding_range() -> None:
    assert pu21_encode(0.0) == pu21_encode(L_MIN)
    assert pu21_encode(1e6) == pu21_encode(L_MAX)
    assert pu21_encode(np.array([-5.0]))[0] >= 0.0


@settings(max_examples=200, deadline=None)
@given(st.floats(L_MIN * 1.01, L_MAX))
def test_reference_decoder_inverts_encode(luminance: float) -> None:
    assert pu21_decode(pu21_encode(luminance)) == pytest.approx(luminance, rel=1e-6)


def test_encode_is_strictly_increasing_and_keeps_shape() -> None:
    luminance = np.geomspace(L_MIN, L_MAX, 1000).reshape(10, 100)
    values = pu21_encode(luminance)
    assert values.shape == (10, 100)
    assert np.all(np.diff(values.ravel()) > 0)


def test_nan_is_refused_not_passed_through() -> None:
    """np.clip passes NaN: pu21_encode([nan, 1]) gave [nan, 36.54]."""
    with pytest.raises(InvalidInputError, match="NaN"):
        pu21_encode(np.array([np.nan, 1.0]))
    with pytest.raises(InvalidInputError, match="NaN"):
        pu21_decode(np.array([np.nan]))


def test_decode_clamps_values_past_the_encodings_range() -> None:
    """pu21_decode(2000) was NaN and pu21_decode(600) above L_MAX."""
    assert pu21_decode(np.array([600.0, 2000.0])) == pytest.approx([L_MAX, L_MAX])
    assert pu21_decode(np.array([-5.0])) == pytest.approx([L_MIN])
