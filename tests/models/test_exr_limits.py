"""Tests of models/exr_limits.py: OpenEXR files refused on their headers, before decoding."""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np
import OpenEXR
import pytest

from models.errors import ImageTooLargeError, InvalidInputError
from models.exr_limits import (
    MAX_EXR_ATTRIBUTES,
    MAX_EXR_HEADER_BYTES,
    MAX_EXR_PARTS,
    check_exr_size,
)
from models.hdr_io import read_hdr

LIMIT = 64 * 64


def exr_bytes(*parts: dict[str, np.ndarray], extra: dict[str, object] | None = None) -> bytes:
    """A multi-part scanline EXR, part i named ``p<i>``, all with a 64 x 64 display window;
    the last part's header also holds the attributes ``extra``."""
    header = {
        "compression": OpenEXR.ZIP_COMPRESSION,
        "type": OpenEXR.scanlineimage,
        "displayWindow": ((0, 0), (63, 63)),
    }
    buffer = io.BytesIO()
    exr_parts = [OpenEXR.Part(dict(header), ch, f"p{i}") for i, ch in enumerate(parts)]
    exr_parts[-1].header.update(extra or {})
    OpenEXR.File(exr_parts).write(buffer)
    return buffer.getvalue()


def plane(side: int) -> np.ndarray:
    return np.ones((side, side), np.float16)


def headers_of(data: bytes) -> list[dict[str, object]]:
    exr = OpenEXR.File(io.BytesIO(data), separate_channels=True, header_only=True)
    return [part.header for part in exr.parts]


def test_a_large_second_part_is_refused() -> None:
    data = exr_bytes({"Y": plane(64)}, {"Z": plane(65)})
    with pytest.raises(ImageTooLargeError, match=r"part 2 \('p1'\).* 65 x 65 = 4225 pixels"):
        read_hdr(data, max_pixels=LIMIT)


def test_the_size_is_refused_before_the_pixels_are_decoded() -> None:
    noise = np.random.default_rng(0).random((256, 256), np.float32)
    data = exr_bytes({"Y": plane(64)}, {"Z": noise})
    with pytest.raises(ImageTooLargeError, match="part 2"):
        read_hdr(data[: len(data) * 3 // 4], max_pixels=LIMIT)


def test_extra_channels_beyond_four_samples_per_pixel_are_refused() -> None:
    five = {name: plane(64) for name in ("Y", "x0", "x1", "x2", "x3")}
    with pytest.raises(ImageTooLargeError, match="20480 samples.*limit of 16384"):
        read_hdr(exr_bytes(five), max_pixels=LIMIT)
    three = {name: plane(64) for name in ("Z", "A", "B")}
    over_parts = exr_bytes({"Y": plane(64)}, three, {"C": plane(8)})
    with pytest.raises(ImageTooLargeError, match="16448 samples"):
        read_hdr(over_parts, max_pixels=LIMIT)


def test_rgba_at_the_limit_and_small_extra_parts_are_read() -> None:
    rgba = {name: plane(64) for name in "RGBA"}
    assert read_hdr(exr_bytes(rgba), max_pixels=LIMIT).pixels.shape == (64, 64, 3)
    with_depth = exr_bytes({"Y": plane(64)}, {"Z": plane(32)}, {"A": plane(32)})
    assert read_hdr(with_depth, max_pixels=LIMIT).pixels.shape == (64, 64)


def test_too_many_parts_are_refused_even_without_a_pixel_limit() -> None:
    data = exr_bytes(*({"Y": plane(2)} for _ in range(MAX_EXR_PARTS + 1)))
    with pytest.raises(ImageTooLargeError, match=f"more than {MAX_EXR_PARTS} parts"):
        read_hdr(data)
    check_exr_size(headers_of(data)[:MAX_EXR_PARTS], max_pixels=None)


def test_subsampled_channels_count_their_stored_samples() -> None:
    headers = headers_of(exr_bytes({name: plane(64) for name in "RGBA"}))
    check_exr_size(headers, max_pixels=LIMIT)
    headers[0]["channels"].append(OpenEXR.Channel("C", 2, 2))  # type: ignore[attr-defined]
    with pytest.raises(ImageTooLargeError, match="17408 samples"):
        check_exr_size(headers, max_pixels=LIMIT)


def numbered(count: int) -> dict[str, object]:
    """``count`` int attributes ``m0``, ``m1``, ..."""
    return {f"m{i}": i for i in range(count)}


def test_a_part_of_too_many_attributes_is_refused_before_the_library_parses_it(
    tmp_path: Path,
) -> None:
    """The library's header parse grows faster than the attribute count, holding the GIL:
    160,000 attributes (2.8 MB) took 18 s and stalled the API."""
    plain = headers_of(exr_bytes({"Y": plane(4)}))[0]
    at_limit = exr_bytes({"Y": plane(4)}, extra=numbered(MAX_EXR_ATTRIBUTES - len(plain)))
    assert read_hdr(at_limit).pixels.shape == (4, 4)
    over = exr_bytes({"Y": plane(4)}, extra=numbered(MAX_EXR_ATTRIBUTES - len(plain) + 1))
    path = tmp_path / "over.exr"
    path.write_bytes(over)
    for source in (over, path):
        with pytest.raises(
            ImageTooLargeError, match=f"part 1 .* more than {MAX_EXR_ATTRIBUTES} header attr"
        ):
            read_hdr(source)
    second = exr_bytes({"Y": plane(4)}, {"Z": plane(4)}, extra=numbered(MAX_EXR_ATTRIBUTES))
    with pytest.raises(ImageTooLargeError, match="part 2 of the OpenEXR file has more than"):
        read_hdr(second)


def test_headers_over_the_byte_limit_are_refused(tmp_path: Path) -> None:
    data = exr_bytes({"Y": plane(4)}, extra={"note": "x" * MAX_EXR_HEADER_BYTES})
    path = tmp_path / "long.exr"
    path.write_bytes(data)
    for source in (data, path):
        with pytest.raises(ImageTooLargeError, match=f"more than {MAX_EXR_HEADER_BYTES} bytes"):
            read_hdr(source)
    shorter = exr_bytes({"Y": plane(4)}, extra={"note": "x" * (MAX_EXR_HEADER_BYTES // 2)})
    assert read_hdr(shorter).pixels.shape == (4, 4)


def test_a_file_ending_in_a_later_part_s_header_is_truncated() -> None:
    data = exr_bytes({"Y": plane(4)}, {"Z": plane(4)}, extra={"note": "x" * 100})
    with pytest.raises(InvalidInputError, match="header is truncated or corrupt"):
        read_hdr(data[: data.index(b"x" * 100) + 50])
