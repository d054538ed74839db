"""Size limits on an OpenEXR file, checked on its headers before any pixel is decoded.

The OpenEXR Python binding (3.5) decodes every part and every channel of a file at once;
it cannot read a single part or channel. A file whose image part is small can therefore
still carry a huge second part or dozens of extra channels. These checks refuse such a
file from its headers alone (``OpenEXR.File(..., header_only=True)``).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

from models.errors import ImageTooLargeError

#: The most parts an accepted OpenEXR file may have (an image plus a few AOVs).
MAX_EXR_PARTS = 16
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


def check_exr_size(headers: Sequence[Mapping[str, Any]], max_pixels: int | None) -> None:
    """Raise :class:`ImageTooLargeError` when decoding the file would exceed the limits.

    Refused: more than :data:`MAX_EXR_PARTS` parts; with ``max_pixels`` set, any part of
    more than ``max_pixels`` pixels, or more than ``MAX_SAMPLES_PER_LIMIT_PIXEL *
    max_pixels`` samples (channels x pixels) over all parts.
    """
    if len(headers) > MAX_EXR_PARTS:
        raise ImageTooLargeError(
            f"the OpenEXR file has {len(headers)} parts, above the limit of {MAX_EXR_PARTS}; "
            + _REMEDY
        )
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
