"""What the parts of an OpenEXR file hold, checked on their headers before decoding.

The OpenEXR Python binding (3.5) decodes every part of a file at once, so a part the
reader cannot use is refused from the headers (``OpenEXR.File(..., header_only=True)``)
before any pixel is decoded, and the part holding the image is chosen there
(:func:`image_part`).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import OpenEXR

from models.errors import UnsupportedFormatError

RGB_CHANNELS = ("R", "G", "B")
#: Chroma channels of a luminance/chroma image (Y, RY, BY), as ImfRgbaYca writes it.
_CHROMA = ("RY", "BY")
_DEEP = (OpenEXR.deepscanline, OpenEXR.deeptile)
#: Channel names an error message lists at most.
_LISTED = 10


def check_flat(headers: Sequence[Mapping[str, Any]]) -> None:
    """Raise :class:`UnsupportedFormatError` when a part is deep (``deepscanline`` or
    ``deeptile``): the binding decodes deep samples into one Python object per pixel
    (640 MB for a 1.2 MB file) and the reader has no way to flatten them."""
    for index, header in enumerate(headers):
        if header.get("type") in _DEEP:
            raise UnsupportedFormatError(
                f"part {index + 1} of the OpenEXR file is deep ({header['type'].name}); deep "
                "OpenEXR is not supported: flatten it to channel Y or R, G, B and send that"
            )


def _image_channels(index: int, header: Mapping[str, Any]) -> tuple[str, ...] | None:
    """The channels of part ``index`` holding the image: R,G,B if present, else Y, else
    None. Raises :class:`UnsupportedFormatError` for a luminance/chroma image."""
    names = {channel.name for channel in header["channels"]}
    if names.issuperset(RGB_CHANNELS):
        return RGB_CHANNELS
    if "Y" not in names:
        return None
    if names.intersection(_CHROMA):
        raise UnsupportedFormatError(
            f"part {index + 1} of the OpenEXR file is luminance/chroma (channels Y, RY, BY), "
            "which is not supported; re-save it as R, G, B (colour) or Y (grayscale)"
        )
    return ("Y",)


def _check_sampling(index: int, header: Mapping[str, Any], names: tuple[str, ...]) -> None:
    """Raise :class:`UnsupportedFormatError` when one of the channels ``names`` of part
    ``index`` is subsampled: the binding returns it smaller than the image (a grayscale
    image came back at half size, a colour one failed as 'truncated or corrupt')."""
    for channel in header["channels"]:
        if channel.name in names and (channel.xSampling, channel.ySampling) != (1, 1):
            raise UnsupportedFormatError(
                f"channel {channel.name} of part {index + 1} of the OpenEXR file is "
                f"subsampled (xSampling {channel.xSampling}, ySampling {channel.ySampling}), "
                "which is not supported; re-save the image with every channel at full "
                "resolution"
            )


def image_part(headers: Sequence[Mapping[str, Any]]) -> tuple[int, tuple[str, ...]]:
    """The index of the first part holding the image, and its channels (Y or R, G, B).

    Raises :class:`UnsupportedFormatError` when no part holds one, or its channels are
    subsampled."""
    for index, header in enumerate(headers):
        channels = _image_channels(index, header)
        if channels is not None:
            _check_sampling(index, header, channels)
            return index, channels
    found = sorted({channel.name for header in headers for channel in header["channels"]})
    raise UnsupportedFormatError(
        f"no part of the OpenEXR file has a Y or R,G,B image (channels: {_listed(found)}); "
        "write the image as channel Y (grayscale) or R, G, B"
    )


def _listed(names: list[str]) -> str:
    """The first :data:`_LISTED` of ``names`` and how many more (3000 channels of long
    names made a 645,129-character message)."""
    more = len(names) - _LISTED
    return ", ".join(names[:_LISTED]) + (f" ... and {more} more" if more > 0 else "")
