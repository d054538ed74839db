"""How many entries a zip's central directory holds, counted without :mod:`zipfile`.

``zipfile.ZipFile`` builds a Python object for every record of the central directory
before a caller can count them (300k entries cost 270 MiB), and it parses as many
records as the directory's byte size allows, whatever entry count the end record
declares. :func:`central_entries` walks the records itself and stops past a limit, so
an upload of 60 MB of tiny records is refused in microseconds instead of costing
600 MB and seconds. Record layouts: PKWARE APPNOTE 6.3.10, sections 4.3.12 (central
directory header), 4.3.14-4.3.16 (ZIP64 end record and locator, end record).
"""

from __future__ import annotations

#: Signatures of the records read here.
_CENTRAL = b"PK\x01\x02"
_END = b"PK\x05\x06"
_END64 = b"PK\x06\x06"
_LOCATOR64 = b"PK\x06\x07"
#: Fixed sizes (bytes): central header, end record, ZIP64 end record (without its
#: extensible data) and its locator.
_CENTRAL_SIZE = 46
_END_SIZE = 22
_END64_SIZE = 56
_LOCATOR64_SIZE = 20
#: The end record sits within its size plus the longest comment of the archive's end.
_END_SEARCH = _END_SIZE + 65_535


def _little(data: bytes, start: int, size: int) -> int:
    return int.from_bytes(data[start : start + size], "little")


def _directory_start(data: bytes) -> int | None:
    """Where the central directory begins (bytes into ``data``), from the end record or
    its ZIP64 counterpart; None when ``data`` has no end record."""
    end = data.rfind(_END, max(0, len(data) - _END_SEARCH))
    if end < 0 or len(data) < end + _END_SIZE:
        return None
    size = _little(data, end + 12, 4)
    locator = end - _LOCATOR64_SIZE
    end64 = locator - _END64_SIZE
    if locator >= 0 and data[locator : locator + 4] == _LOCATOR64 and end64 >= 0:
        if data[end64 : end64 + 4] == _END64:
            return end64 - _little(data, end64 + 40, 8)
    return end - size


def central_entries(data: bytes, most: int) -> int | None:
    """The records of the zip ``data``'s central directory, counted up to ``most + 1``
    (the walk stops there); None when ``data`` has no end record (not a zip: the
    caller's zip reader says so)."""
    start = _directory_start(data)
    if start is None:
        return None
    count, at = 0, max(start, 0)
    while count <= most and data[at : at + 4] == _CENTRAL and at + _CENTRAL_SIZE <= len(data):
        names = _little(data, at + 28, 2) + _little(data, at + 30, 2) + _little(data, at + 32, 2)
        at += _CENTRAL_SIZE + names
        count += 1
    return count
