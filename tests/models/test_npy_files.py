"""Tests of models/npy_files.py: npy files, as wrapped frames are read from them."""

from __future__ import annotations

import io

import numpy as np
import pytest

from models.errors import InvalidInputError
from models.frames import decode_frame, encode_frame
from tests.models.test_frames import PARAMS_8, random_codes


def test_an_npy_of_python_objects_is_not_called_corrupt() -> None:
    """An object array (np.save of frames of several sizes with dtype=object, or of
    codes as Python ints) was 'truncated or corrupt (Object arrays cannot be loaded
    when allow_pickle=False); send the complete, unmodified file': it is neither."""
    buffer = io.BytesIO()
    np.save(buffer, random_codes((6, 5), 8).astype(object), allow_pickle=True)
    with pytest.raises(InvalidInputError, match="holds Python objects") as caught:
        decode_frame(buffer.getvalue(), "npy", PARAMS_8.model_dump())
    assert "corrupt" not in caught.value.message and "np.uint16" in caught.value.message


@pytest.mark.parametrize(
    "tail",
    [b"\x00", bytes(7), encode_frame(np.zeros((6, 5), np.uint8), None, "npy")],
    ids=["one byte", "seven bytes", "a second array"],
)
def test_bytes_after_an_npy_array_are_refused(tail: bytes) -> None:
    """numpy stops at the end of the first array; a second np.save into the same file
    (or a damaged upload) would otherwise be dropped without a word."""
    data = encode_frame(random_codes((6, 5), 8), None, "npy")
    with pytest.raises(InvalidInputError, match=rf"{len(tail)} bytes after its array of shape"):
        decode_frame(data + tail, "npy", PARAMS_8.model_dump())
