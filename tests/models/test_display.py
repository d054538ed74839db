"""Tests of models/display.py: the sRGB transfer curve to 8-bit codes."""

from __future__ import annotations

import numpy as np
import pytest

from models.display import srgb8
from models.errors import InvalidInputError


def test_reference_codes_and_clipping() -> None:
    """The linear segment's end 0.0031308 -> 0.04045 (10.3 DN), 0.5 -> 0.7354 (187.5)."""
    codes = srgb8(np.array([-1.0, 0.0, 0.0031308, 0.5, 1.0, 5.0]))
    assert codes.tolist() == [0, 0, 10, 188, 255, 255]


def test_nan_is_refused_not_drawn_black() -> None:
    with pytest.raises(InvalidInputError, match="NaN"):
        srgb8(np.array([np.nan, 0.5]))
