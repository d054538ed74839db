"""npy files: an array's shape and dtype from the header, read before its data, and the
one array a file holds (no Python objects, nothing after the array); sensor codes
(:func:`npy_codes`) read booleans as 0 and 1.

Wrapped frames (:mod:`models.frames`), winding maps (:mod:`models.winding_files`) and
videos (:mod:`worker.video_input`) are read through it.
"""

from __future__ import annotations

import io
from typing import Any

import numpy as np
from numpy.typing import NDArray

from models.errors import InvalidInputError


def _npy_header(data: bytes) -> tuple[tuple[int, ...], np.dtype[Any]]:
    """The array shape and dtype an npy file's header declares, read before any array
    data."""
    buffer = io.BytesIO(data)
    version = np.lib.format.read_magic(buffer)
    if version == (1, 0):
        shape, _, dtype = np.lib.format.read_array_header_1_0(buffer)
    else:
        shape, _, dtype = np.lib.format.read_array_header_2_0(buffer)
    return tuple(shape), dtype


def npy_shape(data: bytes) -> tuple[int, ...]:
    """The array shape an npy file's header declares, read before any array data (so
    that size limits are checked before the array is loaded)."""
    return _npy_header(data)[0]


def load_npy(data: bytes) -> NDArray[Any]:
    """The one array of an npy file. An array of Python objects (pickled, not read
    here) is refused as such, not as a corrupt file. Bytes after the array are refused:
    numpy would ignore them, and they are most often a second array saved into the
    same file (whose frames would be lost without a word) or a damaged upload."""
    shape, dtype = _npy_header(data)
    if dtype.hasobject:
        raise InvalidInputError(
            f"the npy file holds Python objects (dtype {dtype}, shape {shape}), which are "
            "not read here: save one integer array, e.g. np.save(path, np.asarray(codes, "
            "np.uint16)) (a video's frames stacked, all of one size)"
        )
    buffer = io.BytesIO(data)
    array = np.load(buffer, allow_pickle=False)
    if (extra := len(data) - buffer.tell()) > 0:
        raise InvalidInputError(
            f"the npy file has {extra} bytes after its array of shape {array.shape}; send "
            "a file holding one array (np.save once per file; stack frames into one array)"
        )
    return array


def npy_codes(data: bytes) -> NDArray[Any]:
    """The sensor codes (DN) an npy file holds: its one array (:func:`load_npy`), with
    booleans (a 1-bit frame or video saved as such) read as codes 0 and 1, as 1-bit PNG
    and TIFF frames are read."""
    codes = load_npy(data)
    return codes.astype(np.uint8) if codes.dtype == np.bool_ else codes
