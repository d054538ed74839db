"""What the parts of an OpenEXR file hold, checked on their headers before decoding.

The OpenEXR Python binding (3.5) decodes every part of a file at once, so a part the
reader cannot use is refused from the headers (``OpenEXR.File(..., header_only=True)``)
before any pixel is decoded.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import OpenEXR

from models.errors import UnsupportedFormatError

_DEEP = (OpenEXR.deepscanline, OpenEXR.deeptile)


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
