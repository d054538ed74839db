"""Tests of worker/plane_refinement.py: guided refinement of a stream's W, plane by plane."""

from __future__ import annotations

import numpy as np
from hypothesis import given
from hypothesis import strategies as st
from numpy.typing import NDArray

from models.decoders.base import Decoder
from models.decoders.guided_puma import GuidedPumaDecoder
from models.formation import SensorParams, dequantize, encode
from worker.plane_refinement import grown, refined_planes

PARAMS = SensorParams(encoding="mantissa", max_wraps=64)


class UnusedGuide(Decoder):
    """The refiner's guide: :func:`refined_planes` refines the W it is given, so a
    refinement that asked the guide for its own W would be a bug."""

    name = "unused"  # type: ignore[assignment]

    def predict_winding(self, m: NDArray[np.float64], params: SensorParams) -> NDArray[np.int64]:
        raise AssertionError("refined_planes must not decode the frame again")


def _two_hills() -> tuple[NDArray[np.float64], NDArray[np.int64], NDArray[np.int64]]:
    """m (H x W x 2, the same frame twice), its true W and a guide capped at 2 wraps:
    a 96 x 192 mantissa frame with two smooth hills of several wraps."""
    yy, xx = np.mgrid[0:96, 0:192] / 96.0
    hills = sum(np.exp(-((xx - cx) ** 2 + (yy - 0.5) ** 2) / 0.04) for cx in (0.5, 1.5))
    frame = encode(0.1 + 24.0 * hills, PARAMS)
    m = dequantize(frame.codes, PARAMS.bits)
    truth = np.stack([frame.winding, frame.winding], axis=2).astype(np.int64)
    return np.stack([m, m], axis=2), truth, np.minimum(truth, 2)


def test_whole_planes_reach_the_true_winding() -> None:
    m, truth, guide = _two_hills()
    assert truth.max() >= 4
    refiner = GuidedPumaDecoder(UnusedGuide(), region_moves=0)
    np.testing.assert_array_equal(refined_planes(refiner, m, guide, PARAMS), truth)


def test_each_plane_changes_only_within_its_own_band() -> None:
    """Channel 0's band covers its left hill, channel 1 has none: only that hill moves."""
    m, truth, guide = _two_hills()
    bands = np.zeros(m.shape, bool)
    bands[:, :96, 0] = True
    refiner = GuidedPumaDecoder(UnusedGuide(), region_moves=0)
    refined = refined_planes(refiner, m, guide, PARAMS, bands)
    np.testing.assert_array_equal(refined[:, :96, 0], truth[:, :96, 0])
    np.testing.assert_array_equal(refined[:, 96:, 0], guide[:, 96:, 0])
    np.testing.assert_array_equal(refined[:, :, 1], guide[:, :, 1])


@given(st.integers(0, 3), st.integers(0, 7), st.integers(0, 7))
def test_grown_is_a_chebyshev_band_within_each_plane(reach: int, row: int, col: int) -> None:
    pixels = np.zeros((8, 8, 2), bool)
    pixels[row, col, 0] = True
    band = grown(pixels, reach)
    yy, xx = np.mgrid[0:8, 0:8]
    np.testing.assert_array_equal(band[:, :, 0], np.maximum(abs(yy - row), abs(xx - col)) <= reach)
    assert not band[:, :, 1].any()
