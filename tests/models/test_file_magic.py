"""Tests of models/file_magic.py: formats judged by their leading bytes."""

from __future__ import annotations

import pytest

from models.file_magic import (
    FRAME_MAGICS,
    HDR_MAGICS,
    VIDEO_MAGICS,
    content_first,
    format_by_content,
    named_format,
)


@pytest.mark.parametrize(
    ("data", "magics", "expected"),
    [
        (b"\x89PNG\r\n\x1a\nrest", FRAME_MAGICS, "png"),
        (b"MM\x00+rest", FRAME_MAGICS, "tiff"),
        (b"\x93NUMPY\x01\x00", VIDEO_MAGICS, "npy"),
        (b"PK\x03\x04", VIDEO_MAGICS, "zip"),
        (b"PK\x03\x04", FRAME_MAGICS, None),
        (b"#?RGBE\n", HDR_MAGICS, "hdr"),
        (b"", FRAME_MAGICS, None),
    ],
)
def test_format_by_content(data: bytes, magics: tuple, expected: str | None) -> None:
    assert format_by_content(data, magics) == expected


def test_content_first_keeps_the_name_unless_the_content_says_otherwise(
    caplog: pytest.LogCaptureFixture,
) -> None:
    assert content_first(b"no magic here", "tiff", FRAME_MAGICS) == ("tiff", None)
    assert content_first(b"II*\x00", "tiff", FRAME_MAGICS) == ("tiff", None)
    assert caplog.text == ""
    judged = content_first(b"\x89PNG\r\n\x1a\n", "tiff", FRAME_MAGICS)
    assert judged.format == "png" and judged.warning is not None
    assert "content is PNG although its name or declared format says TIFF" in judged.warning
    assert judged.warning in caplog.text


@pytest.mark.parametrize(
    ("name", "expected"),
    [("frame.TIF", "tiff"), ("a.b.npy", "npy"), ("frame.bmp", None), ("frame", None), (None, None)],
)
def test_a_file_name_names_the_format_its_suffix_aliases(
    name: str | None, expected: str | None
) -> None:
    assert named_format(name, {"tif": "tiff", "tiff": "tiff", "npy": "npy"}) == expected
