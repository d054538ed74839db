"""Winding-number map files (``W``, int64): which suffixes hold one, writing and reading.

Formats
-------
- ``png``: one 16-bit grey channel, 0 <= W <= 65535 (``H x W x 1`` written as ``H x W``).
- ``tiff``: 16-bit, 0 <= W <= 65535, grey or RGB, one page, in the layout
  :func:`models.frames.write_tiff_page` says (every TIFF reader opens it; an int64 one
  Pillow and ImageJ do not).
- ``npy``: int64, any W and shape.

``mcam reconstruct --winding-out``, ``mcam simulate --ground-truth`` and the API's
``part=winding`` downloads write them alike (:func:`encode_winding_file`). The reader
takes any integer samples.

Maps are read as strictly as wrapped frames (:mod:`models.frames`): by their content
first, a TIFF's compression named when not read and its thumbnails skipped; a file
that stores sensor parameters is a wrapped frame and refused.
"""

from __future__ import annotations

import io
import os
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray
from PIL import Image

from models.errors import (
    FormatCannotHoldError,
    InvalidInputError,
    UnsupportedFormatError,
    naming,
)
from models.file_magic import FRAME_MAGICS, content_first, named_else_shown
from models.frames import (
    PNG_KEYWORD,
    PNG_MODES,
    decoding,
    encode_frame,
    frame_format,
    png_samples,
)
from models.npy_files import load_npy
from models.stored_params import tiff_params
from models.tiff_pages import open_tiff, page_codes


def winding_format(name: str | os.PathLike[str]) -> str:
    """The format (``png``, ``tiff`` or ``npy``) of a winding-map file name; another
    suffix is refused as a W map's, not as a wrapped frame's."""
    try:
        return frame_format(name)
    except UnsupportedFormatError:
        raise UnsupportedFormatError(
            f"unsupported winding-map format {str(name)!r}: a W map is .png, .tiff/.tif or "
            ".npy, as mcam reconstruct --winding-out and mcam simulate --ground-truth write it"
        ) from None


#: The largest W a PNG or TIFF W map holds: their samples are 16-bit unsigned.
MAX_IMAGE_WINDING = int(np.iinfo(np.uint16).max)


def encode_winding_file(winding: NDArray[np.integer], fmt: str) -> bytes:
    """The bytes of a W map file of format ``fmt`` (``png``, ``tiff`` or ``npy``, a
    name or suffix too): npy int64 of any W and shape; PNG and TIFF 16-bit, 0 <= W <=
    :data:`MAX_IMAGE_WINDING`, PNG of one channel. :class:`FormatCannotHoldError`
    naming the formats that hold the map when ``fmt`` cannot."""
    arr = np.asarray(winding)
    if arr.dtype.kind not in "iu":
        raise InvalidInputError(f"winding numbers are integers, got dtype {arr.dtype}")
    fmt = winding_format(fmt)
    if fmt == "npy":
        buffer = io.BytesIO()
        np.save(buffer, arr.astype(np.int64), allow_pickle=False)
        return buffer.getvalue()
    if arr.size and (arr.min() < 0 or arr.max() > MAX_IMAGE_WINDING):
        raise FormatCannotHoldError(
            f"a {fmt.upper()} W map holds 16-bit W, 0 to {MAX_IMAGE_WINDING}, and this "
            f"map's W is in [{arr.min()}, {arr.max()}]: write it as .npy (format=npy over "
            "HTTP; int64), which holds any W"
        )
    if fmt == "png" and arr.ndim == 3 and arr.shape[2] > 1:
        raise FormatCannotHoldError(
            f"a PNG W map is grayscale (one channel) and this map has {arr.shape[2]} (a "
            "colour frame's): write it as .tiff or .npy (format=tiff or format=npy over "
            "HTTP), which hold colour W maps"
        )
    return encode_frame(arr.astype(np.uint16), None, fmt)


def write_winding(path: str | os.PathLike[str], winding: NDArray[np.integer]) -> None:
    """Write a W map in the format of ``path``'s suffix (:func:`encode_winding_file`)."""
    Path(path).write_bytes(encode_winding_file(winding, os.fspath(path)))


def read_winding(path: str | os.PathLike[str]) -> NDArray[np.int64]:
    """Read a winding-number map written by :func:`write_winding` (int64); the format is
    its content's, else its suffix's. An error about the file's content names its path."""
    data = Path(path).read_bytes()
    fmt = named_else_shown(str(path), data, FRAME_MAGICS, winding_format)
    with naming(str(path)):
        return decode_winding(data, content_first(data, fmt, FRAME_MAGICS).format)


#: The W maps :func:`decode_winding` reads, in its messages.
_WRITTEN_W = "the W map that mcam reconstruct --winding-out or mcam simulate --ground-truth wrote"


def _check_grey_winding(mode: str) -> None:
    """Refuse a PNG W map of the Pillow ``mode`` when it is not grey: mcam writes W as
    16-bit grey, and the API's colour-coded W preview (RGB) shows W modulo its palette,
    whose colours were read as winding numbers."""
    if mode not in PNG_MODES:
        raise UnsupportedFormatError(
            f"a PNG W map is grey (16-bit, as mcam writes it) and this PNG is {mode}: a "
            "colour-coded preview (GET /v1/jobs/{id}/result?part=winding&format=png) shows "
            "W, it does not store it; ask for format=npy or format=tiff, or give "
            f"{_WRITTEN_W}"
        )


def _tiff_winding(data: bytes) -> tuple[NDArray[Any], bool]:
    """The samples of a TIFF W map's one page, read as a frame's are (its compression
    named when not read, its inflation bounded, thumbnails skipped), and whether it
    stores sensor parameters (a wrapped frame's TIFF)."""
    with open_tiff(data, max_pages=1) as (_, pages):
        if len(pages) > 1:
            raise InvalidInputError(
                f"the TIFF holds more than one page of full resolution and a W map is one: "
                f"give {_WRITTEN_W}"
            )
        (page,) = pages
        return page_codes(page), bool(tiff_params(page.description))


def decode_winding(data: bytes, fmt: str) -> NDArray[np.int64]:
    """A winding-number map (int64) from the bytes of a ``png``, ``tiff`` or ``npy``
    file as :func:`write_winding` writes them. A PNG or TIFF that stores sensor
    parameters is a wrapped frame, refused: its codes read as winding numbers gave a
    winding accuracy without a word."""
    with decoding(f"the {fmt.upper()} winding map"):
        if fmt == "png":
            image = Image.open(io.BytesIO(data), formats=["PNG"])
            _check_grey_winding(image.mode)
            arr, frame = png_samples(image, data), PNG_KEYWORD in image.text
        elif fmt == "tiff":
            arr, frame = _tiff_winding(data)
        else:
            arr, frame = load_npy(data), False
    if frame:
        raise InvalidInputError(
            f"this is a wrapped frame (it stores sensor parameters), not a winding map: give "
            f"{_WRITTEN_W}"
        )
    if arr.dtype.kind not in "iu":
        raise InvalidInputError(f"a winding map holds integers, got dtype {arr.dtype}")
    return arr.astype(np.int64)
