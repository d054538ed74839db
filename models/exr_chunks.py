"""Whether a single-part scanline OpenEXR file holds all its pixel chunks, from its bytes.

The OpenEXR library reports a truncated or corrupt file by printing to the process's
standard error (its C core's default handler, then the Python binding's warning)
before the binding gives up on the part. In a server that is a few lines of log per
bad upload, which a client can repeat at will. :func:`missing_chunks` reads the
header, the chunk offset table and each chunk's leader (scanline and packed size)
itself, so that such a file is refused with a clear error before the library sees
it. Tiled, deep and multi-part files are left to the library (None).
:func:`attribute_parts` walks the headers of any file, multi-part included, for
:func:`models.exr_limits.check_exr_headers`.

Layout (OpenEXR file format, version 2): magic and version (8 bytes); the header's
attributes, each ``name\\0 type\\0 size:int32 value``, ending with an empty name
(a multi-part file: one header per part, the last followed by an empty one);
one little-endian uint64 offset per chunk; then the chunks, each ``y:int32
size:int32`` and ``size`` bytes.
"""

from __future__ import annotations

import struct
from collections.abc import Iterator

#: Version-field flags of a file this module does not check.
_TILED, _DEEP, _MULTIPART = 0x200, 0x800, 0x1000
#: Scanlines per chunk by compression code (none, rle, zips, zip, piz, pxr24, b44,
#: b44a, dwaa, dwab).
_LINES_PER_CHUNK = (1, 1, 1, 16, 32, 16, 32, 32, 32, 256)


def _cstring(data: bytes, at: int) -> tuple[bytes, int]:
    """The NUL-terminated string at ``at`` and the offset past its NUL (ValueError if none)."""
    end = data.index(b"\0", at)
    return data[at:end], end + 1


def _attribute(data: bytes, at: int) -> tuple[bytes, int, int]:
    """The name of the attribute at ``at`` (empty at a header's end), where its value
    starts and the offset past it. ValueError or struct.error where it runs past ``data``."""
    name, at = _cstring(data, at)
    if not name:
        return name, at, at
    _kind, at = _cstring(data, at)
    (size,) = struct.unpack_from("<i", data, at)
    if size < 0 or at + 4 + size > len(data):
        raise ValueError("attribute runs past the file")
    return name, at + 4, at + 4 + size


def _header(data: bytes) -> tuple[dict[bytes, bytes], int]:
    """A single-part header's attribute values by name, and the offset past it."""
    attributes, at = {}, 8
    while True:
        name, start, at = _attribute(data, at)
        if not name:
            return attributes, at
        attributes[name] = data[start:at]


def attribute_parts(data: bytes) -> Iterator[int]:
    """For each header attribute of the OpenEXR file ``data`` (from its magic), in file
    order, the index of its part (0 for a single-part file). Only names and sizes are
    read, one attribute per step, so a caller can stop at a limit. ValueError or
    struct.error where a header runs past the end of ``data``."""
    (version,) = struct.unpack_from("<I", data, 4)
    part, at, empty = 0, 8, True
    while True:
        name, _start, at = _attribute(data, at)
        if name:
            empty = False
            yield part
        elif empty or not version & _MULTIPART:
            return
        else:
            part, empty = part + 1, True


def _chunk_count(attributes: dict[bytes, bytes]) -> int | None:
    """Chunks of a scanline part: its height over the compression's lines per chunk
    (None for a compression newer than this table, e.g. HTJ2K)."""
    _x0, y0, _x1, y1 = struct.unpack("<4i", attributes[b"dataWindow"])
    code = attributes[b"compression"][0]
    if code >= len(_LINES_PER_CHUNK):
        return None
    return -(-(y1 - y0 + 1) // _LINES_PER_CHUNK[code])


def missing_chunks(data: bytes) -> bool | None:
    """Whether the OpenEXR file ``data`` (starting with its magic) is truncated or has a
    chunk table pointing outside it: True, False, or None for a file this module does
    not check (tiled, deep or multi-part, or a compression it does not know). A header
    that cannot be read counts as truncated."""
    if len(data) < 8:
        return True
    (version,) = struct.unpack_from("<I", data, 4)
    if version & (_TILED | _DEEP | _MULTIPART):
        return None
    try:
        attributes, at = _header(data)
        count = _chunk_count(attributes)
        if count is None:
            return None
        table_end = at + 8 * count
        if count < 0 or table_end > len(data):
            return True
        for offset in struct.unpack_from(f"<{count}Q", data, at):
            if offset < table_end or offset + 8 > len(data):
                return True
            (size,) = struct.unpack_from("<i", data, offset + 4)
            if size < 0 or offset + 8 + size > len(data):
                return True
    except (ValueError, KeyError, IndexError, struct.error):
        return True
    return False
