"""Tests of worker/motion.py: the matching cost, texture, the motion estimate and warp."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from models.errors import InvalidInputError
from models.formation import dequantize, encode
from tests.worker.panning import PAN_PARAMS, smooth_scene
from worker.motion import MotionConfig, compensate, misfit, resample, texture


def planes(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(u, m)`` of a noiseless modulo frame as H x W x 1 arrays."""
    frame = encode(x, PAN_PARAMS)
    m = dequantize(frame.codes, PAN_PARAMS.bits)
    return (frame.winding + m)[:, :, None], m[:, :, None]


@settings(max_examples=60, deadline=None)
@given(base=st.floats(0.0, 1.0), wraps=st.integers(-5, 5), error=st.floats(-0.49, 0.49))
def test_misfit_is_the_distance_to_a_whole_number_of_wraps(
    base: float, wraps: int, error: float
) -> None:
    value = misfit(np.array([base + wraps + error]), np.array([base]))
    assert value[0] == pytest.approx(abs(error), abs=1e-9)
    assert 0.0 <= value[0] <= 0.5


def test_texture_ignores_a_brightness_offset_and_wrapping() -> None:
    """Texture of u + c equals texture of u; wrapped texture of m equals u's exact one
    where neighbours differ by less than half a wrap; the step samples it."""
    u = smooth_scene()[:, :, None]
    np.testing.assert_allclose(texture(u + 0.3, wrapped=False), texture(u, wrapped=False),
                               atol=1e-9)
    m = u - np.floor(u)
    np.testing.assert_allclose(texture(m, wrapped=True), texture(u, wrapped=False), atol=1e-9)
    np.testing.assert_array_equal(texture(u, False, step=2), texture(u, False)[::2, ::2])
    assert texture(u, False)[-1, -1, 0] == 0.0


#: The default search (px per frame): a pan this far in each direction is still found.
EDGE = MotionConfig().search


@pytest.mark.parametrize(
    "shift", [(0, 2), (1, -2), (-3, 0), (EDGE, EDGE), (-EDGE, -EDGE), (EDGE, -EDGE)]
)
def test_a_pan_is_found_and_undone(shift: tuple[int, int]) -> None:
    """The current frame shows the previous one moved by ``-shift``: the warped previous
    u equals the current u wherever its source lay inside the previous frame (pans of
    the whole search distance included)."""
    scene = smooth_scene(96, 128)
    prev_u, _ = planes(scene[16:80, 16:80])
    now_u, now_m = planes(scene[16 + shift[0] : 80 + shift[0], 16 + shift[1] : 80 + shift[1]])
    moved = compensate(prev_u, now_m, MotionConfig())
    assert moved.shift == shift
    assert moved.u.shape == prev_u.shape and moved.inside.shape == (64, 64)
    np.testing.assert_allclose(moved.u[moved.inside], now_u[moved.inside])
    entering = np.zeros((64, 64), bool)
    if shift[0] > 0:
        entering[-shift[0] :] = True
    if shift[0] < 0:
        entering[: -shift[0]] = True
    if shift[1] > 0:
        entering[:, -shift[1] :] = True
    if shift[1] < 0:
        entering[:, : -shift[1]] = True
    np.testing.assert_array_equal(moved.inside, ~entering)


def test_a_still_or_brightening_frame_does_not_move() -> None:
    """No motion: the previous u comes back unchanged, also under a brightness offset
    (which matching m itself would mistake for a shift along a gradient)."""
    u, m = planes(smooth_scene()[:, :64])
    still = compensate(u, m, MotionConfig())
    assert still.shift == (0, 0) and still.inside.all() and still.moved == 0.0
    np.testing.assert_array_equal(still.u, u)
    brighter = u + 0.3
    brighter_m = brighter - np.floor(brighter)
    assert compensate(u, brighter_m, MotionConfig()).shift == (0, 0)


def test_search_zero_turns_compensation_off() -> None:
    scene = smooth_scene()
    prev_u, _ = planes(scene[:, :64])
    _, now_m = planes(scene[:, 2:66])
    off = compensate(prev_u, now_m, MotionConfig(search=0))
    assert off.shift == (0, 0) and off.u is prev_u and off.inside.all()


@pytest.mark.parametrize("shape", [(1, 7), (7, 1), (2, 2), (3, 5), (37, 53), (37, 53, 3)])
def test_any_frame_shape_keeps_its_shape(shape: tuple[int, ...]) -> None:
    """Tiny, odd and colour frames: no crash, shapes kept (a 37 x 53 frame pans too)."""
    scene = smooth_scene(64, 128)
    rows, cols = shape[:2]
    prev = scene[:rows, :cols]
    now = scene[:rows, 2 : cols + 2]
    if len(shape) == 3:
        prev, now = np.stack([prev] * 3, axis=2), np.stack([now] * 3, axis=2)
    prev_u = prev if prev.ndim == 3 else prev[:, :, None]
    now_m = now - np.floor(now)
    now_m = now_m if now_m.ndim == 3 else now_m[:, :, None]
    moved = compensate(prev_u, now_m, MotionConfig())
    assert moved.u.shape == prev_u.shape and moved.inside.shape == (rows, cols)
    assert np.isfinite(moved.u).all()
    if rows >= 16 and cols >= 16:
        assert moved.shift == (0, 2)


@pytest.mark.parametrize(
    "bad",
    [{"search": -1}, {"block": 7}, {"block": 0}, {"stride": 0}, {"switch": 0.0},
     {"accept": 0.6}],
)
def test_bad_motion_settings_are_refused(bad: dict) -> None:
    with pytest.raises(InvalidInputError, match="invalid motion settings"):
        MotionConfig(**bad)


@settings(max_examples=40, deadline=None)
@given(
    rows=st.integers(1, 40), cols=st.integers(1, 40), block=st.sampled_from([2, 4, 16]),
    seed=st.integers(0, 2**32 - 1),
)
def test_resample_takes_each_pixel_from_its_blocks_offset(
    rows: int, cols: int, block: int, seed: int
) -> None:
    """Every pixel, in the last, partial blocks too, reads the padded previous frame at
    its own position plus its block's offset, and is inside when that source is."""
    rng = np.random.default_rng(seed)
    pad = 2
    padded = rng.random((rows + 2 * pad, cols + 2 * pad, 2))
    blocks = (-(-rows // block), -(-cols // block), 2)
    offsets = rng.integers(-pad, pad + 1, blocks)
    warped, inside = resample(padded, pad, (rows, cols), offsets, block)
    for y in range(rows):
        for x in range(cols):
            dy, dx = offsets[y // block, x // block]
            np.testing.assert_array_equal(warped[y, x], padded[y + dy + pad, x + dx + pad])
            assert inside[y, x] == (0 <= y + dy < rows and 0 <= x + dx < cols)
