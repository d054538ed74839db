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


def exr_bytes(
    *parts: dict[str, np.ndarray],
    origins: dict[int, tuple[int, int]] | None = None,
    extra: dict[str, object] | None = None,
) -> bytes:
    """A multi-part scanline EXR, part i named ``p<i>``, all with a 64 x 64 display window;
    the last part's header also holds the attributes ``extra``.

    ``origins`` maps a part's index to its data window's top-left corner (x, y) in pixels;
    a part not named there has its data window at (0, 0). The binding replaces the arrays
    of each ``parts`` dictionary by its channel objects: pass a fresh dictionary each time.
    """
    header = {
        "compression": OpenEXR.ZIP_COMPRESSION,
        "type": OpenEXR.scanlineimage,
        "displayWindow": ((0, 0), (63, 63)),
    }
    buffer = io.BytesIO()
    exr_parts = []
    for i, channels in enumerate(parts):
        x0, y0 = (origins or {}).get(i, (0, 0))
        height, width = next(iter(channels.values())).shape
        window = ((x0, y0), (x0 + width - 1, y0 + height - 1))
        exr_parts.append(OpenEXR.Part({**header, "dataWindow": window}, channels, f"p{i}"))
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


#: Data-window origins (x, y) in pixels: each axis once negative, once positive, far
#: enough from 0 that adding the corners instead of subtracting them changes the size.
ORIGINS = [(-200, 100), (100, -200), (-1000, -1000), (1000, 1000)]


@pytest.mark.parametrize("origin", ORIGINS)
def test_a_part_away_from_the_origin_is_measured_from_its_corners(origin: tuple[int, int]) -> None:
    """64 x 64 at the limit is read wherever the window lies; 65 x 64 and 64 x 65 are not."""
    at_limit = exr_bytes({"Y": plane(8)}, {"Z": plane(64)}, origins={1: origin})
    assert read_hdr(at_limit, max_pixels=LIMIT).pixels.shape == (8, 8)
    for width, height in ((65, 64), (64, 65)):
        wide = np.ones((height, width), np.float16)
        over = exr_bytes({"Y": plane(8)}, {"Z": wide}, origins={1: origin})
        refusal = rf"part 2 \('p1'\).* {width} x {height} = {width * height} pixels"
        with pytest.raises(ImageTooLargeError, match=refusal):
            read_hdr(over, max_pixels=LIMIT)
    image_over = exr_bytes({"Y": np.ones((64, 65), np.float16)}, origins={0: origin})
    with pytest.raises(ImageTooLargeError):
        read_hdr(image_over, max_pixels=LIMIT)


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
