"""Tests of models/exr_chunks.py: a scanline OpenEXR file's chunks, checked from its bytes."""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np
import OpenEXR
import pytest

from models.exr_chunks import attribute_parts, missing_chunks
from models.hdr_io import encode_exr

HDRI = Path(__file__).resolve().parents[2] / "models" / "data" / "hdri" / "venice.exr"


@pytest.mark.parametrize("compression", ["zip", "none"])
@pytest.mark.parametrize("shape", [(1, 1), (37, 53, 3), (300, 17)])
def test_a_whole_file_has_every_chunk_and_every_cut_of_it_misses_some(
    compression: str, shape: tuple[int, ...]
) -> None:
    data = encode_exr(np.random.default_rng(1).random(shape), compression=compression)
    assert missing_chunks(data) is False
    assert all(missing_chunks(data[:cut]) is True for cut in range(len(data)))


def test_a_real_dwab_scene_is_whole() -> None:
    """The shared scenes are DWAB-compressed: 256 scanlines a chunk."""
    data = HDRI.read_bytes()
    assert missing_chunks(data) is False
    assert missing_chunks(data[: len(data) - 1]) is True


def test_a_chunk_table_pointing_outside_the_file_is_caught() -> None:
    data = bytearray(encode_exr(np.ones((20, 20)), compression="none"))
    table = len(data) - 20 * (8 + 20 * 4) - 20 * 8  # one chunk per scanline
    data[table : table + 8] = (len(data) + 100).to_bytes(8, "little")
    assert missing_chunks(bytes(data)) is True


def test_multi_part_files_are_left_to_the_library(tmp_path: Path) -> None:
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    parts = [
        OpenEXR.Part(dict(header), {"Y": np.ones((4, 4), np.float32)}, name)
        for name in ("a", "b")
    ]
    path = tmp_path / "two.exr"
    OpenEXR.File(parts).write(str(path))
    assert missing_chunks(path.read_bytes()) is None


def test_the_header_walk_counts_each_part_s_attributes_as_the_library_does() -> None:
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    extras = ({}, {"owner": "me"}, {f"m{i}": i for i in range(40)})
    parts = [
        OpenEXR.Part(dict(header) | extra, {"Y": np.ones((4, 4), np.float32)}, f"p{i}")
        for i, extra in enumerate(extras)
    ]
    buffer = io.BytesIO()
    OpenEXR.File(parts).write(buffer)
    data = buffer.getvalue()
    read = OpenEXR.File(io.BytesIO(data), separate_channels=True, header_only=True)
    walked = list(attribute_parts(data))
    assert [walked.count(i) for i in range(3)] == [len(part.header) for part in read.parts]
    single = encode_exr(np.ones((2, 2)))
    assert len(list(attribute_parts(single))) == len(
        OpenEXR.File(io.BytesIO(single), header_only=True).parts[0].header
    )


KNOWN = ["NO", "RLE", "ZIPS", "ZIP", "PIZ", "PXR24", "B44", "B44A", "DWAA", "DWAB"]
NEWER = [
    name
    for name in ("HTJ2K256", "HTJ2K32", "LJ2K", "ZSTD")
    if hasattr(OpenEXR, f"{name}_COMPRESSION")
]


def _written(compression: str) -> bytes:
    """A 300 x 40 float32 Y image written by the OpenEXR library with ``compression``."""
    header = {"compression": getattr(OpenEXR, f"{compression}_COMPRESSION"),
              "type": OpenEXR.scanlineimage}  # fmt: skip
    buffer = io.BytesIO()
    pixels = np.random.default_rng(2).random((300, 40), dtype=np.float32)
    OpenEXR.File(header, {"Y": pixels}).write(buffer)
    return buffer.getvalue()


@pytest.mark.parametrize("compression", KNOWN)
def test_every_classic_compression_is_judged_whole_and_cut(compression: str) -> None:
    """Lines per chunk differ by compression (1 to 256): the table must match the
    library's own files."""
    data = _written(compression)
    assert missing_chunks(data) is False
    step = max(1, len(data) // 200)
    assert all(missing_chunks(data[:cut]) is True for cut in range(0, len(data), step))


@pytest.mark.parametrize("compression", NEWER)
def test_a_compression_newer_than_the_table_is_left_to_the_library(compression: str) -> None:
    assert missing_chunks(_written(compression)) is None
