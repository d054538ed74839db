"""Tests of worker/zip_directory.py: a zip's directory records counted without zipfile."""

from __future__ import annotations

import io
import struct
import zipfile

import pytest

from worker.zip_directory import central_entries


def archive(names: list[str], comment: bytes = b"") -> bytes:
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w") as out:
        for name in names:
            out.writestr(name, b"x")
        out.comment = comment
    return buffer.getvalue()


@pytest.mark.parametrize("count", [0, 1, 7])
@pytest.mark.parametrize("comment", [b"", b"c" * 300])
def test_counts_what_zipfile_lists(count: int, comment: bytes) -> None:
    data = archive([f"dir/frame_{n}.png" for n in range(count)], comment)
    assert central_entries(data, 100) == len(zipfile.ZipFile(io.BytesIO(data)).infolist())


def test_counts_behind_prepended_bytes() -> None:
    """As zipfile does, the directory is found from the end record's position and size,
    so bytes before the archive (a self-extracting stub) do not hide it."""
    assert central_entries(b"stub" * 100 + archive(["a.png", "b.png"]), 100) == 2


def test_stops_one_past_the_limit() -> None:
    data = archive([f"{n}.png" for n in range(30)])
    assert central_entries(data, 10) == 11 and central_entries(data, 30) == 30


def test_a_forged_directory_is_counted_by_its_records_not_its_declared_count() -> None:
    """100k records of an entry without data, under an end record that declares one:
    zipfile would parse them all (the declared count is not what it reads). The walk
    stops past the limit at once."""
    record = struct.pack("<4s6H3L5H2L", b"PK\x01\x02", 20, 20, 0, 0, 0, 0, 0, 0, 0,
                         5, 0, 0, 0, 0, 0, 0) + b"a.png"
    body = record * 100_000
    data = body + struct.pack("<4s4H2LH", b"PK\x05\x06", 0, 0, 1, 1, len(body), 0, 0)
    assert central_entries(data, 1200) == 1201
    assert central_entries(data, 200_000) == 100_000


def test_a_zip64_directory_is_counted() -> None:
    """Past 65535 entries the end record defers to the ZIP64 one (count 0xFFFF)."""
    data = archive([f"{n}" for n in range(65_600)])
    assert data[-22 + 8 : -22 + 10] == b"\xff\xff"
    assert central_entries(data, 70_000) == 65_600
    assert central_entries(data, 5) == 6


def test_not_a_zip_is_none() -> None:
    assert central_entries(b"not a zip", 10) is None
    assert central_entries(b"", 10) is None
