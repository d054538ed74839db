"""Tests of models/tiff_segments.py: a TIFF page's strips and tiles, checked and
inflated with a bound."""

from __future__ import annotations

import io
import lzma
import struct
import tracemalloc
import zlib
from collections.abc import Callable

import numpy as np
import pytest
import tifffile

from models.errors import ImageTooLargeError, InvalidInputError
from models.tiff_pages import open_tiff, page_codes
from tests.models.test_tiff_pages import GREY, tiff, with_compression


def test_a_compressed_page_is_inflated_once(monkeypatch: pytest.MonkeyPatch) -> None:
    """Each deflate strip was inflated twice: to check that it holds no more than its
    rows, then again by tifffile (a 4096 x 4096 frame read in 275 ms instead of 140)."""
    inflated: list[int] = []
    real_decompress, real_decompressobj = zlib.decompress, zlib.decompressobj

    def decompress(data: bytes, *args: int) -> bytes:
        inflated.append(len(out := real_decompress(data, *args)))
        return out

    class Counted:
        def __init__(self) -> None:
            self.stream = real_decompressobj()

        def decompress(self, data: bytes, max_length: int = 0) -> bytes:
            inflated.append(len(out := self.stream.decompress(data, max_length)))
            return out

        def __getattr__(self, name: str) -> object:
            return getattr(self.stream, name)

    monkeypatch.setattr(zlib, "decompress", decompress)
    monkeypatch.setattr(zlib, "decompressobj", Counted)
    with open_tiff(tiff(GREY, compression="zlib", rowsperstrip=16)) as (tif, _):
        np.testing.assert_array_equal(page_codes(tif.pages.first), GREY)
    assert sum(inflated) == GREY.nbytes


def test_a_cut_short_deflate_strip_is_damage() -> None:
    blank = tiff(np.zeros((64, 64), np.uint8), compression="zlib")
    cut = with_one_segment(blank, zlib.compress(bytes(64 * 64))[:-8])
    with open_tiff(cut) as (tif, _), pytest.raises(zlib.error, match="truncated"):
        page_codes(tif.pages.first)


def with_one_segment(data: bytes, payload: bytes) -> bytes:
    """``data``, a TIFF of one page in one strip or tile, with that segment replaced by
    ``payload`` appended at the end (its offset and byte count tags rewritten)."""
    with tifffile.TiffFile(io.BytesIO(data)) as tif:
        tags = tif.pages.first.tags
        names = ("TileOffsets", "TileByteCounts") if "TileOffsets" in tags else (
            "StripOffsets", "StripByteCounts")
        entries = [tags[name].offset for name in names]
    patched = bytearray(data)
    for entry, value in zip(entries, (len(data), len(payload)), strict=True):
        code = struct.unpack_from("<H", patched, entry)[0]
        struct.pack_into("<HHII", patched, entry, code, 4, 1, value)
    return bytes(patched) + payload


def without_segment(data: bytes, index: int, tag: str) -> bytes:
    """``data``, a TIFF of one page, with entry ``index`` of its ``tag`` (an offsets or
    byte counts tag of SHORTs or LONGs, stored apart from its entry) set to 0."""
    with tifffile.TiffFile(io.BytesIO(data)) as tif:
        found = tif.pages.first.tags[tag]
        where, code = found.valueoffset, "<H" if found.dtype == 3 else "<I"
    patched = bytearray(data)
    struct.pack_into(code, patched, where + struct.calcsize(code) * index, 0)
    return bytes(patched)


@pytest.mark.parametrize(
    ("options", "tag", "refused"),
    [
        ({"tile": (16, 16), "compression": "zlib"}, "TileByteCounts", "tile 1: offset [1-9]"),
        ({"tile": (16, 16)}, "TileOffsets", "tile 1: offset 0"),
        ({"rowsperstrip": 16}, "StripByteCounts", "strip 1: offset [1-9][0-9]*, 0 bytes"),
    ],
    ids=["deflate-tile", "tile-offset", "strip"],
)
def test_a_strip_or_tile_not_stored_is_refused_not_filled_with_zeros(
    options: dict[str, object], tag: str, refused: str
) -> None:
    """A strip or tile of offset or byte count 0 (a writer stopped before it, a sparse
    file) was filled with zeros by tifffile: a quarter of the frame decoded black."""
    data = without_segment(tiff(GREY, **options), 1, tag)
    with open_tiff(data) as (_, pages):
        with pytest.raises(InvalidInputError, match=rf"has 1 of its \d+ .*not stored \({refused}"):
            page_codes(pages[0])


def refused_holding_little(data: bytes, refused: str) -> None:
    """Reading the one page of TIFF ``data`` is refused (:class:`ImageTooLargeError`
    matching ``refused``) while under 16 MiB is held."""
    tracemalloc.start()
    try:
        with open_tiff(data) as (tif, _), pytest.raises(ImageTooLargeError, match=refused):
            page_codes(tif.pages.first)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert peak < 16 * 2**20, f"{peak / 2**20:.0f} MiB held refusing a {len(data)} B TIFF"


@pytest.mark.parametrize(
    "inflate", [lambda raw: zlib.compress(raw, 9), lzma.compress], ids=["deflate", "lzma"]
)
def test_a_strip_inflating_past_its_rows_is_refused_before_it_is_inflated(
    inflate: Callable[[bytes], bytes],
) -> None:
    """A 64 x 64 8-bit frame in one strip holds 4 KiB; a deflate (or LZMA) strip of 64 KB
    (or 10 KB) inflating to 64 MiB was decoded whole by tifffile before it cut the
    rows out (a 522 KB upload took the API past 1 GB with 512 MiB). What is held is the
    LZMA preset's 8 MiB dictionary at most."""
    options = {"compression": "zlib" if inflate is not lzma.compress else "lzma"}
    data = with_one_segment(tiff(np.zeros((64, 64), np.uint8), **options),
                            inflate(bytes(64 * 2**20)))
    refused_holding_little(data, "strip 0 of the TIFF page inflates past")


#: Each byte with its bits in reverse order, by byte value.
REVERSED_BITS = bytes(int(f"{value:08b}"[::-1], 2) for value in range(256))


def fill_order_2(codes: np.ndarray, segment: bytes) -> bytes:
    """A deflate TIFF of ``codes``' shape in one strip, ``segment`` (as deflated), with
    FillOrder 2: its strip stored with each byte's bits reversed."""
    written = tiff(codes, compression="zlib", extratags=[(265, "H", 1, 2, False)])
    with tifffile.TiffFile(io.BytesIO(written)) as tif:
        entry = tif.pages.first.tags[265].offset  # CellLength, tifffile writes it
    patched = bytearray(written)
    struct.pack_into("<H", patched, entry, 266)  # ... as FillOrder (tifffile writes none)
    return with_one_segment(bytes(patched), segment.translate(REVERSED_BITS))


def test_a_fill_order_2_strip_is_bounded_as_tifffile_inflates_it() -> None:
    """tifffile reverses a FillOrder 2 strip's bits before it inflates it; the bound
    inflated the bytes as stored, which did not inflate, and left the strip to tifffile:
    a 64 x 64 frame's 64 KB strip was inflated whole (64 MiB, 141 MiB held) and read."""
    codes = np.arange(64 * 64, dtype=np.uint8).reshape(64, 64)
    with open_tiff(fill_order_2(codes, zlib.compress(codes.tobytes()))) as (tif, _):
        np.testing.assert_array_equal(page_codes(tif.pages.first), codes)
    bomb = fill_order_2(codes, zlib.compress(bytes(64 * 2**20), 9))
    refused_holding_little(bomb, "strip 0 of the TIFF page inflates past")


@pytest.mark.parametrize(
    "payload",
    [b"\x81\0" * 2**19, b"\x81\0" * 2**11, b"\x80" * 2**21],
    ids=["runs-64-MiB", "runs-within-twice-the-strip", "no-ops"],
)
def test_a_packbits_strip_decoding_past_its_rows_is_refused_before_it_is_decoded(
    payload: bytes,
) -> None:
    """tifffile decodes a PackBits strip whole, in Python (a list, 8 bytes an output
    byte): a 64 x 64 frame's one strip of 1 MB of 128-byte runs held 1.2 GB, one of
    2 MB of no-op headers took a Python step a byte. Its runs are counted first, only
    as far as the strip holds, and a strip over twice that is refused unread."""
    blank = with_compression(tiff(np.zeros((64, 64), np.uint8)), 32773)
    refused_holding_little(with_one_segment(blank, payload), "strip 0 of the TIFF page inflates")


def test_an_lzma_strip_asking_for_a_huge_dictionary_is_refused_before_it_is_allocated() -> None:
    """An LZMA strip's header names its dictionary, allocated whole before any output:
    a 345-byte frame naming 4 GiB made the API allocate 4 GiB (or, under a memory
    limit, was 'truncated or corrupt (MemoryError)')."""
    stream = bytearray(lzma.compress(bytes(64 * 64), format=lzma.FORMAT_ALONE))
    struct.pack_into("<I", stream, 1, 2**32 - 1)  # the dictionary size, after the properties
    data = with_one_segment(tiff(np.zeros((64, 64), np.uint8), compression="lzma"), bytes(stream))
    refused_holding_little(
        data, "strip 0 of the TIFF page is LZMA-compressed with a dictionary needing more"
    )


def test_an_lzma_strip_of_several_streams_is_bounded_in_all() -> None:
    """tifffile's ``lzma.decompress`` reads stream after stream: a strip of a 4 KiB
    stream then a 256 MiB one (40 KB) was checked as 4 KiB, then inflated whole (565 MiB
    held). Streams that hold the page between them are read, data after them ignored."""
    codes = np.arange(64 * 64, dtype=np.uint8).reshape(64, 64)
    halves = lzma.compress(codes[:32].tobytes()) + lzma.compress(codes[32:].tobytes())
    blank = tiff(np.zeros((64, 64), np.uint8), compression="lzma")
    with open_tiff(with_one_segment(blank, halves + b"not a stream")) as (tif, _):
        np.testing.assert_array_equal(page_codes(tif.pages.first), codes)
    more = lzma.compress(codes.tobytes()) + lzma.compress(bytes(32 * 2**20))
    refused_holding_little(with_one_segment(blank, more), "strip 0 of the TIFF page inflates")


def test_an_lzma_strip_of_the_largest_preset_is_read() -> None:
    codes = np.arange(64 * 64, dtype=np.uint8).reshape(64, 64)
    stream = lzma.compress(codes.tobytes(), preset=9 | lzma.PRESET_EXTREME)
    data = with_one_segment(tiff(np.zeros((64, 64), np.uint8), compression="lzma"), stream)
    with open_tiff(data) as (tif, _):
        np.testing.assert_array_equal(page_codes(tif.pages.first), codes)


def test_tiles_far_larger_than_their_page_are_refused() -> None:
    """A 16 x 16 page in one 65536 x 65536 tile: its one tile could inflate to 4 GiB
    within the bound of a tile's own size."""
    data = tiff(np.zeros((16, 16), np.uint8), tile=(16, 16), compression="zlib")
    with tifffile.TiffFile(io.BytesIO(data)) as tif:
        entries = [tif.pages.first.tags[name].offset for name in ("TileWidth", "TileLength")]
    patched = bytearray(data)
    for entry in entries:
        code = struct.unpack_from("<H", patched, entry)[0]
        struct.pack_into("<HHII", patched, entry, code, 4, 1, 65536)
    with open_tiff(bytes(patched)) as (tif, _), pytest.raises(ImageTooLargeError,
                                                              match="65536 x 65536"):
        page_codes(tif.pages.first)


def test_tiles_and_strips_of_every_usual_layout_are_read() -> None:
    """A small page in one tile larger than itself, and rows in strips, are read."""
    codes = np.arange(20 * 12, dtype=np.uint16).reshape(20, 12)
    for options in ({"tile": (32, 32)}, {"rowsperstrip": 3}, {"rowsperstrip": 64}):
        with open_tiff(tiff(codes, compression="zlib", **options)) as (tif, _):
            np.testing.assert_array_equal(page_codes(tif.pages.first), codes)
