"""Size limits on an OpenEXR file, checked on its headers before any pixel is decoded.

The OpenEXR Python binding (3.5) decodes every part and every channel of a file at once;
it cannot read a single part or channel. A file whose image part is small can therefore
still carry a huge second part or dozens of extra channels. These checks refuse such a
file from its headers alone (``OpenEXR.File(..., header_only=True)``).

The library's own header parse is bounded first (:func:`check_exr_headers`, on the
file's bytes): it takes time growing faster than the attribute count, holding the GIL
(a 4 x 4 image with 160,000 extra attributes, 2.8 MB: 18 s, stalling every request of
the API), and builds every part's header (40,000 parts, 14.7 MB: +330 MB, 1.9 s).
"""

from __future__ import annotations

import struct
from collections.abc import Mapping, Sequence
from typing import Any

from models.errors import ImageTooLargeError, InvalidInputError
from models.exr_chunks import attribute_parts

#: The most parts an accepted OpenEXR file may have (an image plus a few AOVs).
MAX_EXR_PARTS = 16
#: The most attributes a part's header may hold: the library writes 8-10 (channels,
#: windows, compression, ...), a renderer or compositor a few dozen more.
MAX_EXR_ATTRIBUTES = 512
#: The most bytes all headers of a file may take together (a preview image of 256 x 256
#: takes 256 KiB).
MAX_EXR_HEADER_BYTES = 1 << 20
#: The leading bytes of a file :func:`check_exr_headers` needs: magic and version, the
#: headers at their limit, and one byte more to tell a longer file from one that ends.
EXR_HEAD_BYTES = 8 + MAX_EXR_HEADER_BYTES + 1
#: Samples (channels x pixels, over all parts) allowed per pixel of the pixel limit:
#: R, G, B and A at the limit fit; anything more must fit in fewer pixels.
MAX_SAMPLES_PER_LIMIT_PIXEL = 4

_REMEDY = "write only the image (channel Y, or R, G, B) to the file, as a single part"


def part_size(header: Mapping[str, Any]) -> tuple[int, int]:
    """A part's data window as (width, height) in pixels."""
    (x0, y0), (x1, y1) = header["dataWindow"]
    return max(0, int(x1) - int(x0) + 1), max(0, int(y1) - int(y0) + 1)


def _part_samples(header: Mapping[str, Any]) -> int:
    """Stored samples of one part: each channel's pixels, subsampled as its header says."""
    width, height = part_size(header)
    return sum(
        -(-width // max(1, channel.xSampling)) * -(-height // max(1, channel.ySampling))
        for channel in header["channels"]
    )


def _label(header: Mapping[str, Any], index: int) -> str:
    name = header.get("name")
    return f"part {index + 1} ({name!r})" if isinstance(name, str) else f"part {index + 1}"


def _attribute_counts(head: bytes) -> list[int] | None:
    """Attributes per part of the headers at the start of ``head``, counted until a part
    passes :data:`MAX_EXR_ATTRIBUTES` or the parts pass :data:`MAX_EXR_PARTS`; None when
    the headers run past the end of ``head``."""
    counts: list[int] = []
    try:
        for part in attribute_parts(head):
            if part == len(counts):
                counts.append(0)
            counts[part] += 1
            if len(counts) > MAX_EXR_PARTS or counts[part] > MAX_EXR_ATTRIBUTES:
                break
    except (ValueError, struct.error):
        return None
    return counts


def check_exr_headers(head: bytes) -> None:
    """Refuse an OpenEXR file from its first :data:`EXR_HEAD_BYTES` bytes ``head``, before
    the library parses its headers: :class:`ImageTooLargeError` for more than
    :data:`MAX_EXR_PARTS` parts, more than :data:`MAX_EXR_ATTRIBUTES` attributes in a
    part, or headers longer than :data:`MAX_EXR_HEADER_BYTES` bytes;
    :class:`InvalidInputError` for a file that ends inside its headers."""
    counts = _attribute_counts(head[: EXR_HEAD_BYTES - 1])
    if counts is None and len(head) < EXR_HEAD_BYTES:
        raise InvalidInputError(
            "the OpenEXR header is truncated or corrupt; send the complete file"
        )
    if counts is None:
        raise ImageTooLargeError(
            f"the OpenEXR file's headers take more than {MAX_EXR_HEADER_BYTES} bytes, the "
            "limit; remove large metadata (a preview image, long text attributes) and "
            + _REMEDY
        )
    if len(counts) > MAX_EXR_PARTS:
        raise ImageTooLargeError(
            f"the OpenEXR file has more than {MAX_EXR_PARTS} parts, the limit; " + _REMEDY
        )
    if counts and counts[-1] > MAX_EXR_ATTRIBUTES:
        raise ImageTooLargeError(
            f"part {len(counts)} of the OpenEXR file has more than {MAX_EXR_ATTRIBUTES} "
            "header attributes, the limit; remove the extra metadata and " + _REMEDY
        )


def check_exr_size(headers: Sequence[Mapping[str, Any]], max_pixels: int | None) -> None:
    """Raise :class:`ImageTooLargeError` when decoding the file would exceed the limits.

    With ``max_pixels`` set, refused: any part of more than ``max_pixels`` pixels, or
    more than ``MAX_SAMPLES_PER_LIMIT_PIXEL * max_pixels`` samples (channels x pixels)
    over all parts. (The count of parts is checked on the bytes, by
    :func:`check_exr_headers`.)
    """
    if max_pixels is None:
        return
    for index, header in enumerate(headers):
        width, height = part_size(header)
        if width * height > max_pixels:
            raise ImageTooLargeError(
                f"{_label(header, index)} of the OpenEXR file is {width} x {height} = "
                f"{width * height} pixels, above the limit of {max_pixels}; {_REMEDY}, "
                "or raise the pixel limit (MCAM_MAX_PIXELS)"
            )
    samples = sum(_part_samples(header) for header in headers)
    limit = MAX_SAMPLES_PER_LIMIT_PIXEL * max_pixels
    if samples > limit:
        raise ImageTooLargeError(
            f"the OpenEXR file holds {samples} samples (channels x pixels over all parts), "
            f"above the limit of {limit} ({MAX_SAMPLES_PER_LIMIT_PIXEL} x the pixel limit "
            f"MCAM_MAX_PIXELS); {_REMEDY}"
        )
