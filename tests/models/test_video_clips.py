"""Tests of models/video_clips.py: the seeded synthetic video benchmark set."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from models.errors import InvalidInputError
from models.formation import reconstruct, to_unwrapped
from models.video_clips import (
    CLIP_KINDS,
    SUNRISE_STOPS,
    VIDEO_ENCODINGS,
    _centre_view,
    clip_scene,
    make_clip,
    pan_zoom_frames,
)

FRAMES, SIZE = 4, 32


@pytest.fixture(scope="module", params=CLIP_KINDS)
def clip(request: pytest.FixtureRequest):
    return make_clip(request.param, frames=FRAMES, size=SIZE, seed=3)


def test_shapes_and_dtypes(clip) -> None:
    assert clip.frames == FRAMES
    assert clip.scene.shape == (FRAMES, SIZE, SIZE)
    assert set(clip.encodings) == set(VIDEO_ENCODINGS)
    for enc in clip.encodings.values():
        assert enc.codes.shape == enc.winding.shape == enc.irradiance.shape == clip.scene.shape
        assert enc.codes.dtype == np.uint8 and enc.winding.dtype == np.int64
        assert enc.params.gain is not None and enc.params.seed is None
        assert enc.winding.min() >= 0


def test_ground_truth_reconstructs_within_noise(clip) -> None:
    """Codes plus the true W invert to the true x within quantization and sensor noise."""
    for enc in clip.encodings.values():
        for t in range(FRAMES):
            x_hat = reconstruct(enc.codes[t], enc.winding[t], enc.params)
            error = to_unwrapped(x_hat, enc.params) - to_unwrapped(enc.irradiance[t], enc.params)
            assert np.abs(error).max() < 0.15, "a winding number of the truth is off"


def test_exposure_is_shared_across_encodings_and_frames(clip) -> None:
    gains = {enc.params.gain for enc in clip.encodings.values()}
    assert len(gains) == 1
    enc = clip.encodings["mantissa"]
    np.testing.assert_allclose(enc.irradiance, np.minimum(clip.scene * enc.params.gain, 16.0))


def test_seeded() -> None:
    a = make_clip("static_noise", frames=3, size=16, seed=1)
    b = make_clip("static_noise", frames=3, size=16, seed=1)
    c = make_clip("static_noise", frames=3, size=16, seed=2)
    np.testing.assert_array_equal(a.encodings["modulo"].codes, b.encodings["modulo"].codes)
    assert not np.array_equal(a.encodings["modulo"].codes, c.encodings["modulo"].codes)


def test_static_clip_changes_only_by_noise() -> None:
    clip = make_clip("static_noise", frames=3, size=SIZE)
    enc = clip.encodings["mantissa"]
    np.testing.assert_array_equal(enc.irradiance[0], enc.irradiance[2])
    assert (enc.codes[0] != enc.codes[1]).mean() > 0.3


def test_sunrise_sweeps_wraps_across_the_frame() -> None:
    scene = clip_scene("sunrise", frames=8, size=SIZE)
    np.testing.assert_allclose(scene[-1], scene[0] * 2.0**SUNRISE_STOPS)
    wrapped = make_clip("sunrise", frames=8, size=SIZE).encodings["mantissa"].winding > 0
    fractions = wrapped.mean(axis=(1, 2))
    assert np.all(np.diff(fractions) >= 0) and fractions[0] < 0.05 < 0.25 < fractions[-1]


def test_light_moves() -> None:
    scene = clip_scene("moving_light", frames=8, size=64)
    peaks = [np.unravel_index(np.argmax(frame), frame.shape) for frame in scene]
    assert len(set(peaks)) == 8


def test_pan_zoom_moves_the_view() -> None:
    scene = clip_scene("pan_zoom", frames=3, size=SIZE)
    assert not np.allclose(scene[0], scene[1])
    assert np.corrcoef(np.log(scene[0]).ravel(), np.log(scene[1]).ravel())[0, 1] > 0.7


def test_pan_zoom_wraps_columns_only_and_starts_on_whole_rows() -> None:
    """Rows are a ramp 0..7: frame 0 (the full height) shows them exactly, and no row of
    any frame blends the bottom of the panorama with its top."""
    height, width = 8, 16
    ramp = np.repeat(np.arange(height, dtype=np.float64)[:, None], width, axis=1)
    frames = pan_zoom_frames(ramp, frames=12, size=height)  # pans over the seam at col 16
    np.testing.assert_allclose(frames[0], ramp[:, :height])
    assert frames.min() >= 0 and frames.max() <= height - 1
    assert np.all(np.diff(frames, axis=1) > 0)


def test_centre_view_wraps_columns_and_repeats_edge_rows() -> None:
    height, width, size = 8, 16, 20
    rows, cols = np.mgrid[0:height, 0:width].astype(np.float64)
    view = _centre_view(rows * 100 + cols, size)
    np.testing.assert_array_equal(view[:, 0] // 100, np.clip(np.arange(-6, 14), 0, height - 1))
    np.testing.assert_array_equal(view[0] % 100, np.arange(-2, 18) % width)


@pytest.mark.parametrize(
    ("kind", "frames", "size"), [("dolly", 4, 8), ("static_noise", 1, 8), ("sunrise", 4, 1)]
)
def test_bad_requests_are_refused(kind: str, frames: int, size: int) -> None:
    with pytest.raises(InvalidInputError):
        clip_scene(kind, frames, size)


@settings(max_examples=5, deadline=None)
@given(seed=st.integers(0, 2**31), kind=st.sampled_from(CLIP_KINDS))
def test_any_seed_gives_valid_truth(seed: int, kind: str) -> None:
    enc = make_clip(kind, frames=2, size=8, seed=seed).encodings["modulo"]
    assert np.all(enc.winding <= 16) and np.isfinite(enc.irradiance).all()
