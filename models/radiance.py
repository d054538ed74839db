"""Radiance RGBE (.hdr, .pic) images read, for :func:`models.hdr_io.read_hdr`.

The reader handles new-style run-length-encoded and flat scanlines, and refuses
old-style runs (of early Radiance versions); an RGBE pixel decodes at its mantissa bin
centre, ``(m + 0.5) * 2^(e - 136)``, as Radiance's own ``colr_color`` does. Header
variables (``FORMAT``, ``EXPOSURE``, ...) are returned as attributes; ``EXPOSURE`` is
not divided out. Only the run headers are walked in Python (one step per run); the
bytes of a block of scanlines are expanded by one ``np.repeat``: a 1024 x 512 RLE file
reads 3-5x faster than with a numpy copy per run (docs/changelog.md, session 35).
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

from models.errors import ImageTooLargeError, InvalidInputError, UnsupportedFormatError
from models.frames import check_pixel_count

#: RGBE exponent bias plus the 8 mantissa bits: value = (m + 0.5) * 2^(e - 136).
_RGBE_SHIFT = 136
_RLE_MIN_WIDTH, _RLE_MAX_WIDTH = 8, 0x7FFF
#: The most bytes a Radiance header (to its blank line) may take: a real one is a few
#: lines, and tools add one per command. Split into lines, a 65 MB header of 6 million
#: ``aN=b`` variables took 4-11 s and +1.1 GB.
MAX_RADIANCE_HEADER = 64 * 1024
#: Bytes of Radiance pixels read at a time: bounds the arrays that expand their runs
#: (:func:`_expand_runs`; ``np.repeat`` takes 8 bytes per byte of the file).
_BLOCK_BYTES = 1 << 20

def _radiance_header(data: bytes) -> tuple[dict[str, str], int, int, int, tuple[bool, bool]]:
    """Header variables, (width, height), data offset and (flip rows, flip columns).
    Raises :class:`ImageTooLargeError` for a header over :data:`MAX_RADIANCE_HEADER`."""
    end = data.find(b"\n\n", 0, MAX_RADIANCE_HEADER)
    if end < 0 and len(data) > MAX_RADIANCE_HEADER:
        raise ImageTooLargeError(
            f"the Radiance header runs past {MAX_RADIANCE_HEADER} bytes without the blank line "
            "that ends it; a header is a few lines: remove the extra lines, or convert the "
            "image to OpenEXR"
        )
    if end < 0:
        raise InvalidInputError("the Radiance header has no blank line before the resolution")
    variables: dict[str, str] = {}
    for line in data[:end].decode("latin-1").splitlines()[1:]:
        key, sep, value = line.partition("=")
        if sep and not line.startswith("#"):
            variables[key.strip()] = value.strip()
    if variables.get("FORMAT", "32-bit_rle_rgbe") != "32-bit_rle_rgbe":
        raise UnsupportedFormatError(
            f"Radiance pixel format {variables['FORMAT']} is not supported; convert to RGBE or EXR"
        )
    line_end = data.find(b"\n", end + 2)
    tokens = data[end + 2 : line_end].decode("latin-1").split() if line_end > 0 else []
    if len(tokens) != 4 or tokens[0][1:] != "Y" or tokens[2][1:] != "X":
        raise UnsupportedFormatError(
            f"unsupported Radiance resolution line {' '.join(tokens)!r}; expected '-Y H +X W'"
        )
    try:
        height, width = int(tokens[1]), int(tokens[3])
    except ValueError:
        raise InvalidInputError(f"bad Radiance resolution line {' '.join(tokens)!r}") from None
    return variables, width, height, line_end + 1, (tokens[0][0] == "+", tokens[2][0] == "-")


def _truncated(row: int) -> InvalidInputError:
    return InvalidInputError(
        f"the Radiance file is truncated or corrupt at scanline {row}; send the complete file"
    )


def _rle_headers(
    data: bytes, pos: int, width: int, row: int, repeats: list[int], literals: list[int]
) -> int:
    """Walk the run headers of new-style RLE scanline ``row`` (its four components one
    after the other) from ``pos``, its first header, appending each header's position to
    ``repeats`` (a count above 128: one byte repeated) or ``literals`` (a count of bytes
    that follow); return the position after the scanline. Only the headers are read
    here; :func:`_expand_runs` expands the runs."""
    try:
        for _component in range(4):
            x = 0
            while x < width:
                count = data[pos]
                if count > 128:
                    repeats.append(pos)
                    pos += 2
                    x += count - 128
                elif count:
                    literals.append(pos)
                    pos += 1 + count
                    x += count
                else:
                    raise _truncated(row)
            if x != width:
                raise _truncated(row)
    except IndexError:
        raise _truncated(row) from None
    if pos > len(data):
        raise _truncated(row)
    return pos


def _expand_runs(
    data: bytes, start: int, stop: int, repeats: list[int], literals: list[int]
) -> NDArray[np.uint8]:
    """The bytes that the runs of ``data[start:stop]`` (headers at ``repeats`` and
    ``literals``, positions in ``data``) stand for, in file order: each byte of
    ``data[start:stop]`` repeated by its count (a repeat's value byte its run length, a
    literal's bytes once, headers and other bytes never) in one ``np.repeat``."""
    block = np.frombuffer(data, np.uint8, stop - start, start)
    repeat = np.asarray(repeats, np.intp) - start
    literal = np.asarray(literals, np.intp) - start
    edges = np.zeros(block.size + 1, np.int8)
    edges[literal + 1] = 1
    edges[literal + 1 + block[literal]] = -1
    counts = np.cumsum(edges[:-1], dtype=np.int8).view(np.uint8)
    counts[repeat + 1] = block[repeat] - 128
    return np.repeat(block, counts)


def _refuse_old_style(flat: bytes, row: int) -> None:
    """Raise :class:`UnsupportedFormatError` when the RGBE records of ``flat`` (bytes
    of scanline ``row`` read as flat pixels) hold an old-style run, ``(1, 1, 1, n)``:
    Radiance reads it as "repeat the pixel before", which no normalised pixel is."""
    records = np.frombuffer(flat[: len(flat) // 4 * 4], np.uint8).reshape(-1, 4)
    if (records[:, :3] == 1).all(axis=1).any():
        raise UnsupportedFormatError(
            f"the Radiance file uses old-style run-length encoding (scanline {row}), which "
            "is not supported; convert it to OpenEXR, or re-save it with a current "
            "Radiance tool (e.g. ra_rgbe), which writes new-style runs"
        )


def _flat_scanline(data: bytes, pos: int, width: int, row: int) -> NDArray[np.uint8]:
    """Scanline ``row`` stored flat at ``pos``: RGBE pixels (width x 4)."""
    flat = data[pos : pos + 4 * width]
    _refuse_old_style(flat, row)
    if len(flat) != 4 * width:
        raise _truncated(row)
    return np.frombuffer(flat, np.uint8).reshape(width, 4)


def _is_rle(data: bytes, pos: int, width: int, row: int) -> bool:
    """Whether scanline ``row`` at ``pos`` is new-style RLE (its 4-byte start ``2 2``
    and its width), not flat; a start that declares another width is refused."""
    head = data[pos : pos + 4]
    rle = _RLE_MIN_WIDTH <= width <= _RLE_MAX_WIDTH and head[:2] == b"\x02\x02" and len(head) == 4
    if not (rle and head[2] < 128):
        return False
    if (head[2] << 8 | head[3]) != width:
        raise InvalidInputError(
            f"Radiance scanline {row} declares width {head[2] << 8 | head[3]}, not {width}"
        )
    return True


def _read_rows(data: bytes, pos: int, rows: range, rgbe: NDArray[np.uint8]) -> int:
    """Read scanlines ``rows`` from ``pos`` into ``rgbe`` (height x 4 x width, component
    by component); return the position after them. The run headers of the RLE ones are
    walked first (:func:`_rle_headers`), then their runs expanded all at once."""
    width = rgbe.shape[2]
    start, rle_rows = pos, []
    repeats: list[int] = []
    literals: list[int] = []
    for row in rows:
        if _is_rle(data, pos, width, row):
            pos = _rle_headers(data, pos + 4, width, row, repeats, literals)
            rle_rows.append(row)
        else:
            rgbe[row] = _flat_scanline(data, pos, width, row).T
            pos += 4 * width
    if rle_rows:
        runs = _expand_runs(data, start, pos, repeats, literals)
        rgbe[rle_rows] = runs.reshape(len(rle_rows), 4, width)
    return pos


def _read_scanlines(data: bytes, pos: int, width: int, height: int) -> NDArray[np.uint8]:
    """The RGBE pixels (height x width x 4) of the scanlines from ``pos``, each
    new-style RLE or flat, read :data:`_BLOCK_BYTES` of pixels at a time."""
    rgbe = np.empty((height, 4, width), np.uint8)
    block = max(1, _BLOCK_BYTES // (4 * width))
    for first in range(0, height, block):
        pos = _read_rows(data, pos, range(first, min(first + block, height)), rgbe)
    return rgbe.transpose(0, 2, 1)


def rgbe_to_float(rgbe: NDArray[np.uint8]) -> NDArray[np.float64]:
    """Decode RGBE pixels (``... x 4``): ``(m + 0.5) * 2^(e - 136)``, 0 where ``e == 0``."""
    exponent = rgbe[..., 3].astype(np.int64)
    scale = np.where(exponent > 0, np.ldexp(1.0, exponent - _RGBE_SHIFT), 0.0)
    return (rgbe[..., :3].astype(np.float64) + 0.5) * scale[..., None]


def smallest_scanline(width: int) -> int:
    """The fewest bytes a Radiance scanline of ``width`` pixels can take: new-style RLE
    (a 4-byte start, then per component runs of at most 127 pixels in 2 bytes each)
    where the width allows it, else 4 bytes a pixel."""
    if _RLE_MIN_WIDTH <= width <= _RLE_MAX_WIDTH:
        return 4 + 4 * 2 * -(-width // 127)
    return 4 * width


def read_radiance(data: bytes, max_pixels: int | None) -> tuple[NDArray[Any], dict[str, str]]:
    """The pixels (``H x W x 3``, scene-referred, not yet validated) and header variables
    of a Radiance file's bytes, checked against ``max_pixels`` before any is decoded."""
    variables, width, height, pos, (flip_rows, flip_columns) = _radiance_header(data)
    if width < 1 or height < 1:
        raise InvalidInputError(f"the Radiance image is {width} x {height}; it has no pixels")
    check_pixel_count(width, height, max_pixels)
    if len(data) - pos < height * smallest_scanline(width):
        _refuse_old_style(data[pos : pos + 4 * width], 0)
        raise InvalidInputError(
            f"the Radiance file is truncated or corrupt: its header declares {width} x "
            f"{height} pixels, which take at least {height * smallest_scanline(width)} bytes, "
            f"and {len(data) - pos} bytes follow it; send the complete file"
        )
    pixels = rgbe_to_float(_read_scanlines(data, pos, width, height))
    if flip_rows:
        pixels = pixels[::-1]
    if flip_columns:
        pixels = pixels[:, ::-1]
    return pixels, variables
