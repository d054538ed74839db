"""Tests of worker/frame_message.py: the wire format of a frame on a Redis stream."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from models.errors import InvalidInputError
from models.formation import SensorParams
from worker.frame_message import FrameMessage

PARAMS = SensorParams(encoding="mantissa", alpha=2.0, bits=10)


@given(
    codes=arrays(
        st.sampled_from([np.uint8, np.uint16]),
        st.tuples(st.integers(1, 8), st.integers(1, 8)) | st.tuples(
            st.integers(1, 4), st.integers(1, 4), st.just(3)
        ),
    ),
    sequence=st.integers(0, 2**40),
    discont=st.booleans(),
    bracketed=st.integers(0, 255),
)
def test_fields_round_trip(codes: np.ndarray, sequence: int, discont: bool, bracketed: int) -> None:
    message = FrameMessage("cam-1", sequence, 123, codes, PARAMS, discont, bracketed)
    back = FrameMessage.from_fields({k.encode(): v for k, v in message.to_fields().items()})
    np.testing.assert_array_equal(back.codes, codes)
    assert back.codes.dtype == codes.dtype
    assert (back.device, back.sequence, back.params, back.discont, back.bracketed) == (
        "cam-1", sequence, PARAMS, discont, bracketed
    )


def fields() -> dict[str, bytes]:
    return FrameMessage("cam-1", 7, 0, np.zeros((4, 4), np.uint16), PARAMS).to_fields()


@pytest.mark.parametrize(
    ("change", "expected"),
    [
        ({"shape": None}, "no field 'shape'"),
        ({"dtype": b"<f4"}, "not uint8/uint16"),
        ({"shape": b"4,5"}, "reshape"),
        ({"seq": b"seven"}, "invalid literal"),
        ({"params": b"{not json"}, "malformed frame message"),
    ],
    ids=["missing-field", "float-dtype", "wrong-shape", "bad-seq", "bad-params"],
)
def test_malformed_entries_are_a_clear_error(change: dict, expected: str) -> None:
    entry = {k: v for k, v in {**fields(), **change}.items() if v is not None}
    with pytest.raises(InvalidInputError, match=expected):
        FrameMessage.from_fields(entry)
