"""Tests of models/exr_parts.py: OpenEXR parts the reader cannot use, refused on headers."""

from __future__ import annotations

import io

import numpy as np
import OpenEXR
import pytest

from models.errors import UnsupportedFormatError
from models.hdr_io import read_hdr


def deep_exr(storage: OpenEXR.Storage) -> bytes:
    """A 4 x 5 deep EXR (channel Y) of ``storage``, 0 to 2 samples a pixel."""
    samples = np.empty((4, 5), dtype=object)
    for (row, column), _ in np.ndenumerate(samples):
        samples[row, column] = np.ones((row + column) % 3, np.float32)
    header = {"compression": OpenEXR.ZIPS_COMPRESSION, "type": storage}
    if storage == OpenEXR.deeptile:
        tiles = OpenEXR.TileDescription()
        tiles.xSize = tiles.ySize = 4
        header["tiles"] = tiles
    buffer = io.BytesIO()
    OpenEXR.File(header, {"Y": samples}).write(buffer)
    return buffer.getvalue()


@pytest.mark.parametrize("storage", [OpenEXR.deepscanline, OpenEXR.deeptile])
def test_deep_parts_are_refused_before_decoding(storage: OpenEXR.Storage) -> None:
    """Deep samples were decoded into object arrays, then refused as 'dtype object'."""
    data = deep_exr(storage)
    pattern = f"part 1 .* is deep \\({storage.name}\\).*flatten it to channel Y or R, G, B"
    for upload in (data, data[:-6]):
        with pytest.raises(UnsupportedFormatError, match=pattern):
            read_hdr(upload, max_pixels=10**6)
