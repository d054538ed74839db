"""A PNG's compressed metadata, bounded before Pillow inflates it.

Compressed text (``zTXt``, ``iTXt`` with its compression flag set) and ICC profiles
(``iCCP``) inflate outside the image, whatever its size: Pillow inflates each such
chunk up to 1 MiB (``PngImagePlugin.MAX_TEXT_CHUNK``), text up to 64 MiB a file and ICC
profiles without any bound in all. A 1 MB PNG of 8 x 8 pixels holding 1000 iCCP chunks
of 1 KB each inflated 1 GB (4 s of one of the API's decode slots), and a zip of 50
frames of 66 KB, each with 63 zTXt chunks, 3.2 GB (14 s). :func:`check_metadata`
inflates these chunks itself, stopping at :data:`METADATA_BYTES` for the whole file.
Chunk layouts: PNG (Third Edition) 11.3.3.3 (iCCP), 11.3.3.4 (zTXt), 11.3.3.5 (iTXt).
"""

from __future__ import annotations

import zlib
from collections.abc import Iterator

from models.errors import ImageTooLargeError
from models.file_magic import PNG_SIGNATURE

#: Bytes all compressed metadata of a PNG frame may inflate to: its parameters take a
#: few hundred, an ICC profile a few KB (large ones some hundred KB).
METADATA_BYTES = 1 << 20
#: Chunk types whose data is (or may be) a zlib stream after a keyword.
COMPRESSED_CHUNKS = (b"zTXt", b"iTXt", b"iCCP")


def _compressed_chunks(data: bytes) -> Iterator[tuple[bytes, bytes]]:
    """Each chunk of :data:`COMPRESSED_CHUNKS` in the PNG ``data`` as its type and data
    (others are skipped, not copied), up to ``IEND`` or as far as ``data`` holds whole
    chunk headers (a damaged file is Pillow's to refuse)."""
    at = len(PNG_SIGNATURE)
    while at + 8 <= len(data):
        length = int.from_bytes(data[at : at + 4], "big")
        kind = data[at + 4 : at + 8]
        if kind in COMPRESSED_CHUNKS:
            yield kind, data[at + 8 : at + 8 + length]
        elif kind == b"IEND":
            return
        at += 12 + length  # length, type, data, CRC


def _zlib_stream(kind: bytes, body: bytes) -> bytes | None:
    """The zlib stream of a chunk of :data:`COMPRESSED_CHUNKS` (``body``: its data);
    None when it holds none (an uncompressed iTXt) or is cut short."""
    keyword_end = body.find(b"\0")
    if keyword_end < 0:
        return None
    if kind != b"iTXt":  # keyword, NUL, compression method, stream
        return body[keyword_end + 2 :]
    if body[keyword_end + 1 : keyword_end + 2] != b"\x01":  # the compression flag
        return None
    language_end = body.find(b"\0", keyword_end + 3)
    translated_end = body.find(b"\0", language_end + 1) if language_end >= 0 else -1
    return None if translated_end < 0 else body[translated_end + 1 :]


def check_metadata(data: bytes, most: int = METADATA_BYTES) -> None:
    """Refuse the PNG ``data`` when its compressed text and ICC profile chunks inflate
    to more than ``most`` bytes in all, inflating no more than that. A stream that does
    not inflate is left to Pillow, which says what is wrong with it."""
    left = most
    for kind, body in _compressed_chunks(data):
        stream = _zlib_stream(kind, body)
        if stream is None:
            continue
        try:
            left -= len(zlib.decompressobj().decompress(stream, left + 1))
        except zlib.error:
            continue
        if left < 0:
            raise ImageTooLargeError(
                f"the PNG's compressed metadata (zTXt and iTXt text, iCCP colour profile "
                f"chunks) inflates to more than {most} bytes, where a frame's parameters "
                "take a few hundred: save the frame without that metadata (mcam simulate "
                "-o frame.png writes one)"
            )
