"""Tests of worker/stream_state.py: a stream's memory and the per-frame path shares."""

from __future__ import annotations

import numpy as np
from hypothesis import given
from hypothesis import strategies as st

from models.formation import SensorParams
from worker.stream_state import PATHS, FrameDecode, StreamState, path_shares


def test_reset_forgets_the_frame_but_keeps_the_counts() -> None:
    state = StreamState(np.zeros((2, 2, 1)), SensorParams(), frames=5, last_keyframe=3, sequence=9)
    state.reset()
    assert state.u is None and state.params is None and state.sequence is None
    assert (state.frames, state.last_keyframe) == (5, 3)


@given(st.integers(1, 6), st.integers(1, 6), st.integers(0, 2**16))
def test_path_shares_sum_to_one(height: int, width: int, seed: int) -> None:
    rng = np.random.default_rng(seed)
    local = rng.random((height, width, 1)) < 0.3
    spatial = ~local & (rng.random((height, width, 1)) < 0.3)
    shares = path_shares(local, spatial)
    assert tuple(shares) == PATHS
    assert abs(sum(shares.values()) - 1.0) < 1e-12
    assert shares["local"] == local.mean() and shares["spatial"] == spatial.mean()


def test_a_frame_summary_has_no_arrays() -> None:
    frame = FrameDecode(
        np.zeros((2, 2), np.int64), np.zeros((2, 2)), "first", path_shares(
            np.zeros((2, 2, 1), bool), np.ones((2, 2, 1), bool)
        ), {"total": 10},
    )
    assert frame.summary() == {
        "keyframe": "first",
        "paths": {"temporal": 0.0, "local": 0.0, "spatial": 1.0},
        "timings_ns": {"total": 10},
    }
