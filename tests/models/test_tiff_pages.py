"""Tests of models/tiff_pages.py: the strict TIFF reader of frames and videos."""

from __future__ import annotations

import io
import logging
import re
import struct
import threading
from collections.abc import Callable

import numpy as np
import pytest
import tifffile
from PIL import Image

from models.errors import ImageTooLargeError, InvalidInputError, UnsupportedFormatError
from models.tiff_pages import (
    MAX_SKIPPED_PAGES,
    MAX_TIFF_SEGMENTS,
    TiffDamaged,
    open_tiff,
    page_codes,
    page_shape,
)
from tests.models.test_frames import miniswhite_tiff, random_codes, write_mask


def tiff(array: np.ndarray, **options: object) -> bytes:
    buffer = io.BytesIO()
    tifffile.imwrite(buffer, array, metadata=None, **options)
    return buffer.getvalue()


def test_a_truncated_multi_page_tiff_is_damaged_not_short(
    capsys: pytest.CaptureFixture[str],
) -> None:
    data = tiff(np.zeros((12, 16, 16), np.uint8))
    with pytest.raises(TiffDamaged, match="invalid page offset"):
        with open_tiff(data[: len(data) // 2]):
            pass
    assert capsys.readouterr().err == ""  # tifffile's warning no longer leaks to stderr


def damage_in_a_thread(data: bytes) -> list[BaseException]:
    """What reading ``data`` with :func:`open_tiff` raised in another thread."""
    raised: list[BaseException] = []

    def read() -> None:
        try:
            with open_tiff(data):
                pass
        except TiffDamaged as exc:
            raised.append(exc)

    thread = threading.Thread(target=read)
    thread.start()
    thread.join()
    return raised


def test_damage_is_found_whatever_the_global_log_level(caplog: pytest.LogCaptureFixture) -> None:
    """A root level of CRITICAL kept tifffile from logging its warning: half a video
    was read as a short one. Its logger's own level and propagation come back once
    the last of overlapping reads ends."""
    caplog.set_level(logging.CRITICAL)
    logger = tifffile.logger()
    data = tiff(np.zeros((12, 16, 16), np.uint8))
    with pytest.raises(TiffDamaged, match="invalid page offset"):
        with open_tiff(data[: len(data) // 2]):
            pass
    with open_tiff(data) as (_, pages):
        assert (logger.level, logger.propagate) == (logging.WARNING, False)
        assert len(damage_in_a_thread(data[: len(data) // 2])) == 1
        assert (logger.level, logger.propagate) == (logging.WARNING, False)
    assert len(pages) == 12
    assert (logger.level, logger.propagate) == (logging.NOTSET, True)
    assert caplog.records == []


def test_separate_planes_come_back_samples_last() -> None:
    rgb = np.arange(3 * 4 * 5, dtype=np.uint8).reshape(3, 4, 5)
    with open_tiff(tiff(rgb, photometric="rgb", planarconfig="separate")) as (tif, pages):
        assert len(pages) == 1
        page = tif.pages.first
        assert page_shape(page) == (4, 5, 3)
        np.testing.assert_array_equal(page_codes(page), np.moveaxis(rgb, 0, -1))


def pillow_tiff(array: np.ndarray, compression: str) -> bytes:
    """``array`` as Pillow's libtiff writes it with ``compression``."""
    buffer = io.BytesIO()
    Image.fromarray(array).save(buffer, "TIFF", compression=compression)
    return buffer.getvalue()


def with_short(data: bytes, name: str, value: int, page: int = 0) -> bytes:
    """``data``, a TIFF, with page ``page``'s tag ``name`` set to the SHORT ``value``."""
    with tifffile.TiffFile(io.BytesIO(data)) as tif:
        tag = tif.pages[page].tags[name]
    patched = bytearray(data)
    struct.pack_into("<HHIH", patched, tag.offset, tag.code, 3, 1, value)
    return bytes(patched)


def with_compression(data: bytes, code: int) -> bytes:
    """``data``, a TIFF of one page, with its Compression tag set to ``code``."""
    return with_short(data, "Compression", code)


GREY = np.arange(64 * 48, dtype=np.uint16).reshape(64, 48) * 17
RGB = np.arange(64 * 48 * 3, dtype=np.uint8).reshape(64, 48, 3)


@pytest.mark.parametrize("codes", [GREY, RGB], ids=["grey16", "rgb8"])
@pytest.mark.parametrize(
    "write",
    [
        lambda codes: tiff(codes),
        lambda codes: tiff(codes, compression="zlib"),
        lambda codes: tiff(codes, compression="deflate"),
        lambda codes: tiff(codes, compression="lzma"),
        lambda codes: tiff(codes, compression="zlib", predictor=True),
        lambda codes: tiff(codes, compression="lzma", tile=(16, 16)),
        lambda codes: pillow_tiff(codes, "raw"),
        lambda codes: pillow_tiff(codes, "tiff_adobe_deflate"),
        lambda codes: pillow_tiff(codes, "tiff_deflate"),
        lambda codes: pillow_tiff(codes, "lzma"),
        lambda codes: pillow_tiff(codes, "packbits"),
    ],
    ids=["none", "zlib", "deflate", "lzma", "zlib-predictor", "lzma-tiles", "pillow-raw",
         "pillow-adobe-deflate",
         "pillow-deflate", "pillow-lzma", "pillow-packbits"],
)
def test_every_accepted_compression_is_read(
    write: Callable[[np.ndarray], bytes], codes: np.ndarray
) -> None:
    with open_tiff(write(codes)) as (tif, _):
        np.testing.assert_array_equal(page_codes(tif.pages.first), codes)


@pytest.mark.parametrize(
    ("data", "named"),
    [
        (pillow_tiff(RGB, "tiff_lzw"), "LZW (5)"),
        (pillow_tiff(RGB, "zstd"), "ZSTD (50000)"),
        (pillow_tiff(RGB, "jpeg"), "JPEG (7)"),
        (with_compression(tiff(GREY), 34926), "ZSTD_DEPRECATED (34926)"),
        (with_compression(tiff(GREY), 50001), "WEBP (50001)"),
        (with_compression(tiff(GREY, compression="zlib"), 50013), "PIXTIFF (50013)"),
        (with_compression(tiff(GREY), 12345), "of unknown code 12345"),
    ],
    ids=["lzw", "zstd", "jpeg", "zstd-old-code", "webp", "pixtiff", "unknown"],
)
def test_any_other_compression_is_refused_by_name(data: bytes, named: str) -> None:
    """A Zstandard TIFF was 'truncated or corrupt (No module named 'compression')' on
    Python 3.11, a code of no known compression was 'truncated or corrupt', and a
    PixTIFF one (deflate under another code) was inflated whole, past any bound."""
    accepted = "the compressions accepted are none, deflate (zlib), PackBits, LZMA"
    message = re.escape(f"compression {named}; {accepted}")
    with open_tiff(data) as (tif, _), pytest.raises(UnsupportedFormatError, match=message):
        page_codes(tif.pages.first)


def pillow_palette_tiff(codes: np.ndarray) -> bytes:
    """``codes`` (uint8) saved by Pillow as an indexed-colour TIFF, as an editor's
    "indexed" mode does: its samples are indices into a palette, not the codes."""
    buffer = io.BytesIO()
    Image.fromarray(codes).convert("P", palette=Image.Palette.ADAPTIVE).save(buffer, "TIFF")
    return buffer.getvalue()


@pytest.mark.parametrize(
    ("data", "named"),
    [
        (pillow_palette_tiff(RGB[..., 0]), r"indices into its colour map .*PALETTE"),
        (tiff(np.zeros((8, 8, 4), np.uint8), photometric="separated"), r"CMYK\).*SEPARATED"),
        (tiff(RGB, photometric="ycbcr"), r"YCbCr values \(photometric YCBCR\)"),
        (with_short(tiff(GREY), "PhotometricInterpretation", 8), r"L\*a\*b\*.*CIELAB"),
    ],
    ids=["palette", "cmyk", "ycbcr", "cielab"],
)
def test_samples_that_are_not_grey_or_rgb_values_are_refused_naming_them(
    data: bytes, named: str
) -> None:
    """A palette TIFF's indices were decoded as codes without a word (a palette PNG is
    refused), and YCbCr values as RGB."""
    with open_tiff(data) as (_, pages):
        with pytest.raises(UnsupportedFormatError, match=rf"{named}.*save the image as grey"):
            page_codes(pages[0])


@pytest.mark.parametrize("bits", [12, 10, 24, 0, 33])
def test_samples_of_a_size_not_read_are_refused_naming_it(bits: int) -> None:
    """A 12-bit packed frame was refused as truncated or corrupt ("packints_decode of
    12-bit integers requires the 'imagecodecs' package"), and one of 0 or 33 bits was
    read as no samples (refused as "an array of shape (0,)")."""
    with open_tiff(with_short(tiff(GREY), "BitsPerSample", bits)) as (_, pages):
        with pytest.raises(UnsupportedFormatError, match=rf"samples of {bits} bits.*8- or 16"):
            page_codes(pages[0])


@pytest.mark.parametrize(("most", "counted"), [(None, 12), (20, 12), (12, 12), (5, 6), (0, 1)])
def test_pages_are_counted_up_to_one_past_the_limit(most: int | None, counted: int) -> None:
    """Past ``max_pages`` the count stops at one more: the caller refuses the file
    without indexing the rest."""
    buffer = io.BytesIO()
    with tifffile.TiffWriter(buffer) as writer:
        for _ in range(12):
            writer.write(np.zeros((4, 4), np.uint8))
    with open_tiff(buffer.getvalue(), max_pages=most) as (_, pages):
        assert len(pages) == counted


def test_reduced_resolution_pages_and_masks_are_skipped_up_to_a_bound_per_image() -> None:
    """Thumbnails and pyramid levels (NewSubfileType bit 0) and transparency masks (bit
    2, with bit 0 or not) are not images; each is indexed, so an upload of millions of
    them is refused, not indexed for seconds."""
    def pyramid(levels: int) -> bytes:
        buffer = io.BytesIO()
        with tifffile.TiffWriter(buffer) as writer:
            writer.write(np.full((8, 8), 5, np.uint8), metadata=None)
            for level in range(levels):
                if level % 2:
                    write_mask(writer, (1, 1), (4, 5)[level % 4 // 2])
                else:
                    writer.write(np.zeros((1, 1), np.uint8), subfiletype=1, metadata=None)
            writer.write(np.full((8, 8), 6, np.uint8), metadata=None)
        return buffer.getvalue()

    with open_tiff(pyramid(2 * MAX_SKIPPED_PAGES)) as (_, pages):
        assert [int(page_codes(page)[0, 0]) for page in pages] == [5, 6]
    with pytest.raises(ImageTooLargeError, match="reduced-resolution pages"):
        with open_tiff(pyramid(2 * MAX_SKIPPED_PAGES + 1)):
            pass


def one_row_strips(pages: int, rows: int) -> bytes:
    """A TIFF of ``pages`` pages of ``rows`` x 2 8-bit pixels, a row a strip, every strip
    of every page the same 2 bytes (7, 9): a file of 8 bytes a strip."""
    offsets = 16
    counts = offsets + 4 * rows
    first_ifd = counts + 4 * rows
    entries = (
        (256, 3, 1, 2), (257, 4, 1, rows), (258, 3, 1, 8), (259, 3, 1, 1), (262, 3, 1, 1),
        (273, 4, rows, offsets), (277, 3, 1, 1), (278, 3, 1, 1), (279, 4, rows, counts),
    )  # fmt: skip
    ifd_size = 2 + 12 * len(entries) + 4
    data = bytearray(b"II*\0" + struct.pack("<I", first_ifd) + bytes([7, 9]) + bytes(6))
    data += struct.pack(f"<{rows}I", *[8] * rows) + struct.pack(f"<{rows}I", *[2] * rows)
    for page in range(pages):
        following = first_ifd + (page + 1) * ifd_size if page + 1 < pages else 0
        data += struct.pack("<H", len(entries))
        for tag, kind, count, value in entries:
            width = 2 if kind == 3 and count == 1 else 4  # a SHORT sits left in the 4 bytes
            data += struct.pack("<HHI", tag, kind, count)
            data += value.to_bytes(width, "little").ljust(4, b"\0")
        data += struct.pack("<I", following)
    return bytes(data)


def test_a_tiff_page_of_too_many_strips_is_refused_before_any_is_decoded() -> None:
    """8 million one-row strips of a 2 x 8M frame (32 MB) took 22 s and +2.2 GB to
    decode; the bound is a page's."""
    with open_tiff(one_row_strips(2, 3)) as (tif, pages):
        assert len(pages) == 2
        np.testing.assert_array_equal(page_codes(tif.pages[1]), [[7, 9]] * 3)
    with open_tiff(one_row_strips(1, MAX_TIFF_SEGMENTS)) as (_, pages):
        assert len(pages) == 1
    too_many = rf"page 0 of the TIFF is stored in {MAX_TIFF_SEGMENTS + 1} strips or tiles"
    with pytest.raises(ImageTooLargeError, match=too_many):
        with open_tiff(one_row_strips(1, MAX_TIFF_SEGMENTS + 1)):
            pass


def test_a_video_of_many_strips_in_all_is_read() -> None:
    """600 frames of 512 rows, a row a strip: 307,200 strips, more than a page may hold
    but 512 a page (a file of 72 kB: every strip the same 2 bytes)."""
    assert 600 * 512 > MAX_TIFF_SEGMENTS
    with open_tiff(one_row_strips(600, 512)) as (tif, pages):
        assert len(pages) == 600
        np.testing.assert_array_equal(page_codes(tif.pages[599]), [[7, 9]] * 512)


def with_size(data: bytes, page: int, rows: int, columns: int) -> bytes:
    """``data``, a TIFF, with page ``page``'s ImageLength and ImageWidth tags set to
    ``rows`` and ``columns`` (as LONGs)."""
    with tifffile.TiffFile(io.BytesIO(data)) as tif:
        tags = tif.pages[page].tags
        entries = {tags[name].offset: value
                   for name, value in (("ImageLength", rows), ("ImageWidth", columns))}
    patched = bytearray(data)
    for entry, value in entries.items():
        code = struct.unpack_from("<H", patched, entry)[0]
        struct.pack_into("<HHII", patched, entry, code, 4, 1, value)
    return bytes(patched)


@pytest.mark.parametrize(("page", "rows", "columns"), [(0, 0, 2), (0, 3, 0), (0, 0, 0), (1, 0, 2)])
def test_a_page_of_no_rows_or_no_columns_is_refused_naming_its_size(
    page: int, rows: int, columns: int
) -> None:
    """A frame of 0 rows was refused as "an array of shape (0,)", and such a page of a
    video as differing in size from its first page ("0 x 0 against 3 x 2")."""
    data = with_size(one_row_strips(2, 3), page, rows, columns)
    empty = rf"page {page} of the TIFF is {rows} x {columns} pixels \(rows x columns\)"
    with pytest.raises(InvalidInputError, match=empty):
        with open_tiff(data):
            pass


@pytest.mark.parametrize("tile", [None, (2, 16, 16)])
def test_a_volume_of_slices_is_refused_not_read_as_a_colour_frame(
    tile: tuple[int, int, int] | None,
) -> None:
    """A volume (ImageDepth 3) of 16 x 3 slices was read as one 3 x 16 RGB frame."""
    volume = np.arange(3 * 16 * 3, dtype=np.uint8).reshape(3, 16, 3)
    data = tiff(volume, volumetric=True, photometric="minisblack", tile=tile)
    refused = r"page 0 of the TIFF is a volume of 3 slices of 16 x 3 pixels \(ImageDepth 3\)"
    with pytest.raises(InvalidInputError, match=refused):
        with open_tiff(data):
            pass


def test_a_bilevel_tiffs_codes_are_integers() -> None:
    """A 1-bit TIFF (a 1-bit sensor's frame as Pillow or a camera writes it) read as
    booleans, refused as 'codes must be integers ... not normalized floats'."""
    codes = np.random.default_rng(0).integers(0, 2, (5, 7)).astype(np.uint8)
    buffer = io.BytesIO()
    Image.fromarray(codes.astype(bool)).save(buffer, format="TIFF")
    with open_tiff(buffer.getvalue(), max_pages=1) as (tif, _):
        read = page_codes(tif.pages.first)
    assert read.dtype == np.uint8
    np.testing.assert_array_equal(read, codes)


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16, np.uint32, np.bool_])
def test_a_miniswhite_pages_codes_are_what_it_stands_for_not_as_stored(dtype: type) -> None:
    """A MinIsWhite page was read as stored: its codes came out as 255 - code."""
    codes = (GREY % 2 if dtype is np.bool_ else GREY % 200).astype(dtype)
    stored = ~codes if dtype is np.bool_ else np.iinfo(dtype).max - codes
    with open_tiff(miniswhite_tiff(stored)) as (_, pages):
        assert int(pages[0].photometric) == tifffile.PHOTOMETRIC.MINISWHITE
        np.testing.assert_array_equal(page_codes(pages[0]), codes)


def test_booleans_tifffile_writes_by_default_read_as_other_readers_show_them() -> None:
    """tifffile writes a boolean array MinIsWhite unless told otherwise (True black):
    its codes are what Pillow and viewers show, not the booleans as stored."""
    values = random_codes((5, 7), 1).astype(bool)
    buffer = io.BytesIO()
    tifffile.imwrite(buffer, values)
    shown = np.asarray(Image.open(io.BytesIO(buffer.getvalue())))
    with open_tiff(buffer.getvalue()) as (_, pages):
        np.testing.assert_array_equal(page_codes(pages[0]), shown)
        np.testing.assert_array_equal(page_codes(pages[0]), ~values)


@pytest.mark.parametrize("dtype", [np.float32, np.int16])
def test_miniswhite_samples_of_no_codes_are_refused_naming_minisblack(dtype: type) -> None:
    with open_tiff(miniswhite_tiff(GREY.astype(dtype))) as (_, pages):
        with pytest.raises(UnsupportedFormatError, match=r"MinIsWhite.*save the image as grey"):
            page_codes(pages[0])
