"""Tests of models/winding_files.py: winding-number map files."""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np
import pytest
import tifffile
from PIL import Image

from models.errors import FormatCannotHoldError, InvalidInputError, UnsupportedFormatError
from models.winding_files import (
    decode_winding,
    encode_winding_file,
    read_winding,
    write_winding,
)
from tests.models.test_frames import random_codes


def test_a_1_bit_tiff_winding_map_is_read_as_0_and_1() -> None:
    """tifffile reads a 1-bit TIFF as booleans: such a W map (of a frame that wraps at
    most once) was refused as "a winding map holds integers, got dtype bool"."""
    values = random_codes((5, 7), 1)
    buffer = io.BytesIO()
    tifffile.imwrite(buffer, values.astype(bool), photometric="minisblack")
    winding = decode_winding(buffer.getvalue(), "tiff")
    assert winding.dtype == np.int64
    np.testing.assert_array_equal(winding, values)


def test_a_tiff_winding_map_is_read_as_strictly_as_a_tiff_frame() -> None:
    """An LZW W map was 'truncated or corrupt (... requires the imagecodecs package)',
    and two pages were stacked into a W map of shape 2 x H x W; its thumbnail is
    skipped, as a frame's."""
    winding = random_codes((8, 8), 4)
    buffer = io.BytesIO()
    Image.fromarray(winding).save(buffer, "TIFF", compression="tiff_lzw")
    with pytest.raises(UnsupportedFormatError, match=r"compression LZW \(5\).*deflate"):
        decode_winding(buffer.getvalue(), "tiff")
    for thumbnail in (True, False):
        buffer = io.BytesIO()
        with tifffile.TiffWriter(buffer) as tif:
            tif.write(winding, metadata=None)
            tif.write(winding[::2, ::2], subfiletype=int(thumbnail), metadata=None)
        if thumbnail:
            np.testing.assert_array_equal(decode_winding(buffer.getvalue(), "tiff"), winding)
        else:
            with pytest.raises(InvalidInputError, match="more than one page.*--winding-out"):
                decode_winding(buffer.getvalue(), "tiff")


def test_a_colour_png_is_not_taken_for_a_winding_map() -> None:
    """The API's colour-coded W preview (an RGB PNG) was read as a W map of 3 channels:
    its palette's colours compared with a colour frame's W as winding numbers."""
    preview = io.BytesIO()
    Image.fromarray(random_codes((4, 4, 3), 8)).save(preview, format="PNG")
    with pytest.raises(UnsupportedFormatError, match="PNG is RGB.*format=npy"):
        decode_winding(preview.getvalue(), "png")


def test_a_winding_map_of_another_format_is_refused_as_a_w_map(tmp_path: Path) -> None:
    """It was "unsupported wrapped-frame format 'w.exr'; use one of: .png (grayscale),
    .tiff/.tif (grey or RGB), .npy": the W map called a wrapped frame."""
    (tmp_path / "w.exr").write_bytes(b"v/1\x01")
    path = tmp_path / "w.exr"
    for call in (lambda: read_winding(path), lambda: write_winding(path, np.zeros((2, 2), int))):
        with pytest.raises(UnsupportedFormatError) as caught:
            call()
        assert caught.value.message.startswith("unsupported winding-map format")
        assert "a W map is .png, .tiff/.tif or .npy" in caught.value.message


@pytest.mark.parametrize(
    ("suffix", "winding"),
    [
        ("png", np.array([[0, 1], [65535, 7]])),
        ("tiff", np.array([[0, 65535], [70, 1]])),
        ("npy", np.array([[-3, 70_000], [2**40, 0]])),
        ("npy", np.arange(12).reshape(2, 2, 3)),
        ("tiff", np.arange(36).reshape(4, 3, 3) * 1000),
    ],
)
@pytest.mark.filterwarnings("error")
def test_winding_round_trip(tmp_path: Path, suffix: str, winding: np.ndarray) -> None:
    """Without a warning: a colour TIFF W map emitted tifffile's DeprecationWarning that
    its layout would change (RGB guessed from the shape, unless told)."""
    path = tmp_path / f"w.{suffix}"
    write_winding(path, winding)
    back = read_winding(path)
    assert back.dtype == np.int64
    np.testing.assert_array_equal(back, winding)


@pytest.mark.parametrize("suffix", ["png", "tiff"])
@pytest.mark.filterwarnings("error")
def test_a_one_channel_winding_map_is_written_as_one_grey_image(
    tmp_path: Path, suffix: str
) -> None:
    """H x W x 1 is written H x W. As TIFF it was a 3 x 1 image of 4 separate planes
    (tifffile's guess from the shape 4 x 3 x 1, with a DeprecationWarning); other
    software read it so."""
    winding = np.arange(12).reshape(4, 3, 1)
    write_winding(tmp_path / f"w.{suffix}", winding)
    np.testing.assert_array_equal(read_winding(tmp_path / f"w.{suffix}"), winding[:, :, 0])
    if suffix == "tiff":
        with tifffile.TiffFile(tmp_path / "w.tiff") as tif:
            (page,) = tif.pages
            assert page.shape == (4, 3)
            assert page.photometric == tifffile.PHOTOMETRIC.MINISBLACK


@pytest.mark.filterwarnings("error")
def test_a_colour_winding_tiff_is_one_rgb_page_of_contiguous_samples(tmp_path: Path) -> None:
    write_winding(tmp_path / "w.tiff", np.arange(36).reshape(4, 3, 3))
    with tifffile.TiffFile(tmp_path / "w.tiff") as tif:
        (page,) = tif.pages
        assert page.shape == (4, 3, 3)
        assert page.photometric == tifffile.PHOTOMETRIC.RGB
        assert page.planarconfig == tifffile.PLANARCONFIG.CONTIG


def test_winding_png_refuses_what_it_cannot_hold(tmp_path: Path) -> None:
    for winding in (np.array([[70_000]]), np.array([[-1]])):
        with pytest.raises(FormatCannotHoldError, match="PNG W map holds 16-bit W.*npy"):
            write_winding(tmp_path / "w.png", winding)
    with pytest.raises(FormatCannotHoldError, match="grayscale.*tiff or .npy"):
        write_winding(tmp_path / "w.png", np.zeros((2, 2, 3), np.int64))
    with pytest.raises(InvalidInputError, match="integers"):
        write_winding(tmp_path / "w.npy", np.zeros((2, 2)))
    (tmp_path / "bad.png").write_bytes(b"\x89PNG\r\n\x1a\n")
    with pytest.raises(InvalidInputError):
        read_winding(tmp_path / "bad.png")


@pytest.mark.parametrize("winding", [np.array([[0, 7], [65535, 1]]), np.ones((2, 3, 3), int)])
def test_a_tiff_winding_map_is_16_bit_as_the_api_s(tmp_path: Path, winding: np.ndarray) -> None:
    """mcam wrote int64 TIFF W maps, which Pillow (and ImageJ) cannot open, while the
    API's part=winding&format=tiff is 16-bit: the two now write the same file."""
    write_winding(tmp_path / "w.tiff", winding)
    data = (tmp_path / "w.tiff").read_bytes()
    assert data == encode_winding_file(winding, "tiff")
    with Image.open(tmp_path / "w.tiff") as image:
        assert image.size == (winding.shape[1], winding.shape[0])
    with tifffile.TiffFile(tmp_path / "w.tiff") as tif:
        assert tif.pages[0].dtype == np.uint16
    np.testing.assert_array_equal(read_winding(tmp_path / "w.tiff"), winding)


@pytest.mark.parametrize("winding", [np.array([[70_000]]), np.array([[-1]])])
def test_a_tiff_winding_map_refuses_w_past_16_bits(tmp_path: Path, winding: np.ndarray) -> None:
    with pytest.raises(FormatCannotHoldError, match=r"TIFF W map holds 16-bit W.*\.npy"):
        write_winding(tmp_path / "w.tiff", winding)


def test_a_winding_map_without_a_suffix_is_read_by_its_content(tmp_path: Path) -> None:
    """``mcam evaluate --winding w`` (no suffix, or a pipe) was "unsupported
    winding-map format" though its bytes show the format."""
    winding = np.array([[0, 3], [2, 9]])
    write_winding(tmp_path / "w.tiff", winding)
    (tmp_path / "w.tiff").rename(tmp_path / "w")
    np.testing.assert_array_equal(read_winding(tmp_path / "w"), winding)
    (tmp_path / "notes").write_bytes(b"no map here")
    with pytest.raises(UnsupportedFormatError, match="unsupported winding-map format"):
        read_winding(tmp_path / "notes")


def test_a_winding_map_is_read_by_its_content_whatever_its_name(tmp_path: Path) -> None:
    winding = np.array([[0, 3], [-2, 9]])
    write_winding(tmp_path / "w.npy", winding)
    (tmp_path / "w.npy").rename(tmp_path / "w.tiff")
    np.testing.assert_array_equal(read_winding(tmp_path / "w.tiff"), winding)
