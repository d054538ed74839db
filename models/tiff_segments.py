"""TIFF strips and tiles (segments) of a page, checked and inflated with a bound, for
:func:`models.tiff_pages.page_codes`.

- A page with a strip or tile not stored (offset or byte count 0: a writer stopped
  before it, or a sparse file), which tifffile fills with zeros, is refused
  (:func:`check_segments_stored`).
- tifffile inflates a deflate, LZMA or PackBits strip or tile whole before it cuts out
  the rows the page needs: :func:`models.tiff_pages.page_codes` refuses tiles far
  larger than their page before decoding (:func:`check_segment_sizes`), and inflates
  each segment itself (:func:`inflated_once`), once, as tifffile would (LZMA: all its
  streams together), but only as far as the segment holds: one that inflates past it,
  or an LZMA one whose decoder asks for more than :data:`LZMA_MEMORY_LIMIT`, is
  refused; tifffile decodes the inflated bytes as an uncompressed segment's (unpacking,
  predictor, padding).
"""

from __future__ import annotations

import copy
import lzma
import zlib
from collections.abc import Callable
from typing import Any

import numpy as np
import tifffile
from numpy.typing import NDArray

from models.errors import ImageTooLargeError, InvalidInputError


def separate_planes(page: tifffile.TiffPage) -> bool:
    """Whether ``page`` stores its samples in separate planes (``C x H x W``)."""
    return page.planarconfig == tifffile.PLANARCONFIG.SEPARATE and page.samplesperpixel > 1


#: The most memory (bytes) an LZMA strip or tile may ask its decoder for: its header
#: names a dictionary, allocated whole before any output (up to 4 GiB from a
#: 345-byte upload). xz -9 (the largest preset) needs 65 MiB, the default -6 9 MiB.
LZMA_MEMORY_LIMIT = 1 << 27
#: What CPython's lzma raises (as :class:`lzma.LZMAError`) past its ``memlimit``.
_LZMA_MEMORY_EXCEEDED = "Memory usage limit exceeded"
#: How many times a page's own bytes its strips or tiles may hold in all (padding), and
#: a floor (bytes) for small pages: a 16 x 16 page may come in one 256 x 256 tile.
SEGMENT_SLACK = 4
SEGMENT_SLACK_FLOOR = 1 << 20


def _sample_bytes(page: tifffile.TiffPage) -> int:
    """Bytes of one sample of ``page`` (at least 1)."""
    return max(1, -(-int(page.bitspersample) // 8))


def _segment_samples(page: tifffile.TiffPage) -> tuple[str, str, int]:
    """``page``'s segments: their kind ("tile" or "strip"), their size as text ("width x
    rows"), and how many samples one holds (a strip's rows cut to the page's)."""
    planes = 1 if separate_planes(page) else int(page.samplesperpixel)
    if page.is_tiled:
        width, rows = int(page.tilewidth), int(page.tilelength) * max(1, int(page.tiledepth))
        return "tile", f"{width} x {rows}", width * rows * planes
    rows = min(int(page.rowsperstrip), int(page.imagelength))
    return "strip", f"{int(page.imagewidth)} x {rows}", int(page.imagewidth) * rows * planes


class _LzmaMemoryExceeded(Exception):
    """An LZMA stream's decoder needs more than :data:`LZMA_MEMORY_LIMIT`."""


class _PastBound(Exception):
    """A segment inflates past the bytes it holds."""


def _inflate_deflate(data: bytes, most: int) -> bytes:
    """The deflate stream of ``data`` inflated, as tifffile's ``zlib.decompress`` reads
    it (one stream, data after it ignored), but only to ``most + 1`` bytes:
    :class:`_PastBound` past ``most``, :class:`zlib.error` as that raises when it does
    not inflate."""
    stream = zlib.decompressobj()
    inflated = stream.decompress(data, most + 1)
    if len(inflated) > most:
        raise _PastBound
    if not stream.eof:
        raise zlib.error("Error -5 while decompressing data: incomplete or truncated stream")
    return inflated


def _inflate_lzma(data: bytes, most: int) -> bytes:
    """The LZMA streams of ``data`` inflated, read as tifffile's ``lzma.decompress``
    reads them: stream after stream (two streams of 4 KiB and 256 MiB, 40 KB in all, were
    checked as 4 KiB, then inflated whole), up to data that is not one; but only to
    ``most + 1`` bytes in all (:class:`_PastBound` past ``most``).
    :class:`_LzmaMemoryExceeded` if a stream's decoder needs more than
    :data:`LZMA_MEMORY_LIMIT`; :class:`lzma.LZMAError` as ``lzma.decompress`` raises
    when the first does not inflate or one is cut short."""
    parts: list[bytes] = []
    size = 0
    while True:
        stream = lzma.LZMADecompressor(memlimit=LZMA_MEMORY_LIMIT)
        try:
            part = stream.decompress(data, most + 1 - size)
        except lzma.LZMAError as exc:
            if str(exc) == _LZMA_MEMORY_EXCEEDED:
                raise _LzmaMemoryExceeded from None
            if parts:  # data after the streams: ignored, as lzma.decompress does
                break
            raise
        parts.append(part)
        size += len(part)
        if size > most:
            raise _PastBound
        if not stream.eof:
            raise lzma.LZMAError(
                "Compressed data ended before the end-of-stream marker was reached"
            )
        data = stream.unused_data
        if not data:
            break
    return b"".join(parts)


def _unpack_bits(data: bytes, most: int) -> bytes:
    """The PackBits runs of ``data`` decoded, as tifffile decodes them (a run cut short
    gives what is there), but only to ``most + 1`` bytes (:class:`_PastBound` past
    ``most``): tifffile decodes a segment whole, in Python, into a list of 8 bytes an
    output byte (a 64 x 64 frame's one strip of 2 MB held 1.2 GB). Data longer than
    twice ``most`` is past it unread: every run (but a no-op header, which no writer
    emits) decodes to at least half its length, and a strip of no-op headers decodes to
    nothing after a Python step a byte."""
    if len(data) > 2 * most:
        raise _PastBound
    unpacked = bytearray()
    position = 0
    while position < len(data) and len(unpacked) <= most:
        header = data[position]
        if header < 128:  # a literal run of header + 1 bytes
            unpacked += data[position + 1 : position + header + 2]
            position += header + 2
        elif header > 128:  # one byte repeated 257 - header times
            unpacked += data[position + 1 : position + 2] * (257 - header)
            position += 2
        else:  # a no-op
            position += 1
    if len(unpacked) > most:
        raise _PastBound
    return bytes(unpacked)


#: Each byte with its bits in reverse order, by byte value: tifffile reverses the bits of
#: a FillOrder 2 page's segments so before it inflates them.
_REVERSED_BITS = bytes(int(f"{value:08b}"[::-1], 2) for value in range(256))

#: The inflaters (:func:`_inflate_deflate`, :func:`_inflate_lzma`, :func:`_unpack_bits`)
#: by TIFF code, for the compressions tifffile inflates without bound (each segment
#: whole, past its size): deflate (8, and its old code), LZMA and PackBits.
INFLATERS: dict[int, Callable[[bytes, int], bytes]] = {
    8: _inflate_deflate,
    32946: _inflate_deflate,
    34925: _inflate_lzma,
    32773: _unpack_bits,
}


def check_segment_sizes(page: tifffile.TiffPage) -> None:
    """Refuse ``page`` (:class:`ImageTooLargeError`) when its strips or tiles hold more
    than :data:`SEGMENT_SLACK` times its own bytes (and 1 MiB): a 16 x 16 page in one
    65536 x 65536 tile could inflate to 4 GiB within the bound of the tile's size."""
    kind, size, samples = _segment_samples(page)
    most = samples * _sample_bytes(page)
    page_bytes = int(np.prod(page.shape, dtype=np.int64)) * _sample_bytes(page)
    if len(page.dataoffsets) * most > SEGMENT_SLACK * page_bytes + SEGMENT_SLACK_FLOOR:
        raise ImageTooLargeError(
            f"the TIFF page of {page_bytes} bytes is stored in {len(page.dataoffsets)} "
            f"{kind}s of {size} samples ({most} bytes each), far more than it holds; re-save "
            f"it with {kind}s no larger than the image"
        )


def check_segments_stored(page: tifffile.TiffPage) -> None:
    """Refuse (:class:`InvalidInputError`) ``page`` when one of its strips or tiles is
    not stored (offset 0 or 0 bytes: a file whose writer stopped before it, or one
    written sparse): tifffile fills such a segment with zeros, and a frame missing a
    tile was decoded with a black quarter without a word."""
    # Tags of differing lengths are damage tifffile warns about (TiffDamaged).
    segments = list(zip(page.dataoffsets, page.databytecounts, strict=False))
    missing = [index for index, (offset, count) in enumerate(segments) if not offset or not count]
    if not missing:
        return
    kind = _segment_samples(page)[0]
    offset, count = segments[missing[0]]
    raise InvalidInputError(
        f"the TIFF page has {len(missing)} of its {len(segments)} {kind}s not stored "
        f"({kind} {missing[0]}: offset {offset}, {count} bytes), which a reader fills with "
        "zeros: the file's writer stopped before writing them, or wrote it sparse; send "
        "the frame written whole"
    )


def _stored_plain(page: tifffile.TiffPage) -> tifffile.TiffPage:
    """``page`` as if its strips or tiles were stored uncompressed, in FillOrder 1:
    tifffile's decoding of such a page (unpacking, predictor, tiles' padding) is what
    an inflated segment still needs."""
    plain = copy.copy(page)
    plain.compression = tifffile.COMPRESSION.NONE
    plain.fillorder = 1
    for cached in ("decode", "hash"):  # tifffile's, computed from the two just set
        plain.__dict__.pop(cached, None)
    return plain


def inflated_once(page: tifffile.TiffPage, inflate: Callable[[bytes, int], bytes]) -> NDArray[Any]:
    """``page``'s samples as tifffile gives them, each strip or tile inflated once by
    ``inflate``, as tifffile would inflate it (a FillOrder 2 segment with its bits
    reversed), but refused (:class:`ImageTooLargeError`) past the bytes it holds (a 64 x
    64 frame's one deflate strip of 522 KB inflated 512 MiB at once in tifffile), or
    when its LZMA decoder needs more than :data:`LZMA_MEMORY_LIMIT`. The bound was
    checked by inflating each segment before tifffile inflated it again: a 4096 x 4096
    deflate frame took 275 ms to read instead of 140."""
    kind, size, samples = _segment_samples(page)
    most = samples * _sample_bytes(page)
    decode_plain = _stored_plain(page).decode
    reversed_bits = page.fillorder == 2

    def decode(data: bytes, index: int, **options: Any) -> Any:
        try:
            inflated = inflate(data.translate(_REVERSED_BITS) if reversed_bits else data, most)
        except _LzmaMemoryExceeded:
            raise _lzma_memory_error(f"{kind} {index}") from None
        except _PastBound:
            raise ImageTooLargeError(
                f"{kind} {index} of the TIFF page inflates past the {most} bytes a {kind} "
                f"of {size} samples holds; send the frame as written, without data after "
                "its pixels"
            ) from None
        return decode_plain(inflated, index, **options)

    page.__dict__["decode"] = decode  # tifffile's asarray decodes each segment with it
    try:
        return page.asarray()
    finally:
        del page.__dict__["decode"]


def _lzma_memory_error(where: str) -> ImageTooLargeError:
    """The refusal of the LZMA segment ``where`` ("strip 3") whose decoder needs more
    than :data:`LZMA_MEMORY_LIMIT`."""
    return ImageTooLargeError(
        f"{where} of the TIFF page is LZMA-compressed with a dictionary needing more "
        f"than {LZMA_MEMORY_LIMIT >> 20} MiB to decode; re-save it with deflate, or with "
        "LZMA at one of its presets (0 to 9: the largest needs 65 MiB)"
    )
