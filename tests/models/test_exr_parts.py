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


def exr_of(channels: dict[str, np.ndarray | OpenEXR.Channel]) -> bytes:
    """A single-part scanline EXR of ``channels``."""
    buffer = io.BytesIO()
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    OpenEXR.File(header, channels).write(buffer)
    return buffer.getvalue()


PLANE = np.ones((4, 6), np.float32)


@pytest.mark.parametrize("chroma", [("RY", "BY"), ("RY",)])
def test_a_luminance_chroma_image_is_refused(chroma: tuple[str, ...]) -> None:
    """Y, RY, BY was read as a grayscale image of its luminance."""
    data = exr_of({"Y": PLANE} | {name: PLANE * 0.1 for name in chroma})
    with pytest.raises(UnsupportedFormatError, match="luminance/chroma.*re-save it as R, G, B"):
        read_hdr(data)


def test_colour_channels_beside_chroma_are_read() -> None:
    data = exr_of({name: PLANE * k for k, name in enumerate(("R", "G", "B", "Y", "RY"), 1)})
    np.testing.assert_array_equal(read_hdr(data).pixels[0, 0], [1, 2, 3])


@pytest.mark.parametrize(
    ("channels", "named"),
    [
        ({"Y": OpenEXR.Channel("Y", PLANE, 2, 2)}, "channel Y .*xSampling 2, ySampling 2"),
        ({"R": PLANE, "G": OpenEXR.Channel("G", PLANE, 2, 1), "B": PLANE},
         "channel G .*xSampling 2, ySampling 1"),
    ],
    ids=["gray", "colour"],
)  # fmt: skip
def test_subsampled_image_channels_are_refused(
    channels: dict[str, np.ndarray | OpenEXR.Channel], named: str
) -> None:
    """A subsampled Y came back at half size; a subsampled G as 'truncated or corrupt'."""
    with pytest.raises(UnsupportedFormatError, match=f"{named}.*every channel at full resolution"):
        read_hdr(exr_of(channels))


def test_a_subsampled_channel_beside_the_image_is_read() -> None:
    data = exr_of({"Y": PLANE * 2, "A": OpenEXR.Channel("A", PLANE, 2, 2)})
    np.testing.assert_array_equal(read_hdr(data).pixels, PLANE * 2)


def test_the_channels_of_a_file_without_an_image_are_listed_briefly() -> None:
    """Every name was listed: 645,129 characters for 3000 channels."""
    data = exr_of({f"layer{i:03d}.Z": PLANE for i in range(25)})
    with pytest.raises(UnsupportedFormatError) as raised:
        read_hdr(data)
    listed = ", ".join(f"layer{i:03d}.Z" for i in range(10))
    assert f"(channels: {listed} ... and 15 more);" in raised.value.message
