"""Tests of models/png_chunks.py: a PNG's compressed metadata, bounded before Pillow."""

from __future__ import annotations

import io
import zlib

import numpy as np
import pytest
from PIL import Image, PngImagePlugin

from models.errors import ImageTooLargeError
from models.file_magic import PNG_SIGNATURE
from models.png_chunks import check_metadata
from tests.models.test_frames import png_chunk


def with_chunks(*chunks: bytes) -> bytes:
    """An 8 x 8 grey PNG with ``chunks`` after its IHDR."""
    buffer = io.BytesIO()
    Image.fromarray(np.zeros((8, 8), np.uint8)).save(buffer, "PNG")
    png = buffer.getvalue()
    ihdr_end = len(PNG_SIGNATURE) + 12 + 13  # IHDR: length, type, 13 bytes, CRC
    return png[:ihdr_end] + b"".join(chunks) + png[ihdr_end:]


def zeros(size: int) -> bytes:
    """A zlib stream inflating to ``size`` zero bytes."""
    return zlib.compress(bytes(size), 9)


@pytest.mark.parametrize(
    ("kind", "head"),
    [
        (b"iCCP", b"icc\0\0"),  # profile name, NUL, compression method, then the stream
        (b"zTXt", b"key\0\0"),  # the same layout
        (b"iTXt", b"key\0\x01\0en\0Key\0"),  # flag, method, language, translated keyword
    ],
)
def test_compressed_metadata_past_the_bound_is_refused(kind: bytes, head: bytes) -> None:
    png = with_chunks(*[png_chunk(kind, head + zeros(600)) for _ in range(2)])
    check_metadata(png, 1200)
    with pytest.raises(ImageTooLargeError, match="inflates to more than 1000 bytes"):
        check_metadata(png, 1000)


def test_uncompressed_text_and_damaged_streams_are_not_counted() -> None:
    """An uncompressed iTXt holds no stream; a stream that does not inflate is Pillow's
    to refuse."""
    png = with_chunks(
        png_chunk(b"iTXt", b"key\0\0\0en\0Key\0" + bytes(5000)),
        png_chunk(b"zTXt", b"key\0\0not a zlib stream"),
    )
    check_metadata(png, 10)


def test_a_frame_with_its_text_and_a_colour_profile_passes() -> None:
    """What real PNGs hold (parameters as text, an ICC profile of some KB) is far below
    the bound."""
    info = PngImagePlugin.PngInfo()
    info.add_text("mantissacam", '{"encoding": "mantissa"}', zip=True)
    buffer = io.BytesIO()
    Image.fromarray(np.zeros((8, 8), np.uint8)).save(
        buffer, "PNG", pnginfo=info, icc_profile=bytes(range(256)) * 16
    )
    check_metadata(buffer.getvalue())
