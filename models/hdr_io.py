"""HDR image files: read OpenEXR (single- and multi-part) and Radiance RGBE, write OpenEXR.

Pixels are scene-referred linear values (float64 in memory), ``H x W`` (EXR
channel ``Y``) or ``H x W x 3`` (``R``, ``G``, ``B``). Every image read is checked
with :func:`models.formation.validate_irradiance`: NaN and inf are rejected,
negatives are rejected unless the caller asks to clip them (lossy EXR
compression leaves some), and the clipped count is reported.

The Radiance reader handles new-style run-length-encoded and flat scanlines, and
refuses old-style runs (of early Radiance versions); an RGBE pixel decodes at its
mantissa bin centre, ``(m + 0.5) * 2^(e - 136)``, as Radiance's own ``colr_color``
does. Header variables (``FORMAT``, ``EXPOSURE``, ...) are returned as attributes;
``EXPOSURE`` is not divided out. Only the run headers are walked in Python (one
step per run); the bytes of a block of scanlines are expanded by one ``np.repeat``:
a 1024 x 512 RLE file reads 3-5x faster than with a numpy copy per run (docs/changelog.md,
session 35).
"""

from __future__ import annotations

import io
import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import OpenEXR
from numpy.typing import NDArray

from models.errors import ImageTooLargeError, InvalidInputError, McamError, UnsupportedFormatError
from models.exr_chunks import missing_chunks
from models.exr_limits import EXR_HEAD_BYTES, check_exr_headers, check_exr_size, part_size
from models.exr_parts import check_flat, image_part
from models.file_magic import FRAME_MAGICS, HDR_MAGICS, format_by_content
from models.formation import validate_irradiance
from models.frames import check_pixel_count, decoding
from models.output_range import ensure_fits

_EXR_TRUNCATED = "the OpenEXR pixel data is truncated or corrupt; send the complete file"
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
#: EXR compressions a writer may choose, both lossless. ``zip`` is the smaller file,
#: ``none`` the faster write: on a 256x256 float32 frame (2026-11-26, AMD EPYC) ZIP took
#: 3-5 ms for 225 KiB, none 0.8 ms for 260 KiB (float32 pixels compress by only ~14%).
#: A live stream's worker spent 31% of its time in ZIP (py-spy, bench.stream with itoh).
EXR_COMPRESSIONS: dict[str, Any] = {
    "zip": OpenEXR.ZIP_COMPRESSION,
    "none": OpenEXR.NO_COMPRESSION,
}
#: The compression of EXR files unless a caller chooses another: files that travel to
#: users (a live stream's stored frames default to ``worker.outputs.STREAM_EXR_COMPRESSION``).
DEFAULT_EXR_COMPRESSION = "zip"


@dataclass
class HdrImage:
    """A linear HDR image: float64 pixels, string header attributes, negatives clipped."""

    pixels: NDArray[np.float64]
    attributes: dict[str, str] = field(default_factory=dict)
    negatives_clipped: int = 0


def _exr_file(source: Path | bytes, header_only: bool) -> Any:
    """The binding's file; :class:`UnsupportedFormatError` when header text is not UTF-8."""
    stream = io.BytesIO(source) if isinstance(source, bytes) else str(source)
    try:
        return OpenEXR.File(stream, separate_channels=True, header_only=header_only)
    except UnicodeDecodeError as exc:
        raise UnsupportedFormatError(
            f"text in the OpenEXR header (an attribute or a name) is not UTF-8: byte "
            f"0x{exc.object[exc.start]:02x} in {bytes(exc.object[:40])!r}; re-save the file "
            "with UTF-8 metadata"
        ) from None


def _exr_head(source: Path | bytes) -> bytes:
    """The first :data:`EXR_HEAD_BYTES` bytes of an OpenEXR file (its headers)."""
    if isinstance(source, bytes):
        return source[:EXR_HEAD_BYTES]
    with source.open("rb") as handle:
        return handle.read(EXR_HEAD_BYTES)


def _read_exr(source: Path | bytes, max_pixels: int | None) -> tuple[NDArray[Any], dict[str, str]]:
    """Pixels and string attributes of the first part holding Y or R,G,B.

    The headers' parts, attributes and bytes are counted on the file's bytes
    (:func:`check_exr_headers`) before the library parses them. Bytes (an upload)
    missing pixel chunks are refused before the library reads them
    (:func:`models.exr_chunks.missing_chunks`: it would print its complaint to stderr).
    Every part is checked on the headers (:func:`check_flat`, :func:`check_exr_size`)
    before the binding decodes all parts and channels.
    """
    check_exr_headers(_exr_head(source))
    if isinstance(source, bytes) and missing_chunks(source):
        raise InvalidInputError(_EXR_TRUNCATED)
    headers = [part.header for part in _exr_file(source, header_only=True).parts]
    check_flat(headers)
    index, names = image_part(headers)
    check_pixel_count(*part_size(headers[index]), max_pixels)
    check_exr_size(headers, max_pixels)
    parts = _exr_file(source, header_only=False).parts
    if len(parts) != len(headers):
        # OpenEXR.File drops a part whose pixel data fails to decode instead of raising.
        raise InvalidInputError(_EXR_TRUNCATED)
    channels = parts[index].channels
    planes = [channels[name].pixels for name in names]
    pixels = planes[0] if len(planes) == 1 else np.stack(planes, axis=2)
    header = headers[index]
    return pixels, {key: value for key, value in header.items() if isinstance(value, str)}


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


def _read_radiance(data: bytes, max_pixels: int | None) -> tuple[NDArray[Any], dict[str, str]]:
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


def read_hdr(
    source: str | os.PathLike[str] | bytes,
    *,
    clip_negative: bool = False,
    max_pixels: int | None = None,
    name: str = "",
) -> HdrImage:
    """Read an OpenEXR or Radiance (.hdr/.pic) image from a path or bytes; format by magic.

    ``name`` labels error messages (defaults to the path). Raises
    :class:`UnsupportedFormatError`, :class:`ImageTooLargeError` or
    :class:`InvalidInputError` (truncated, corrupt, NaN/inf/negative pixels).
    """
    if isinstance(source, bytes):
        label, head = name or "the HDR image", source[:16]
    else:
        source = Path(source)
        with source.open("rb") as handle:
            label, head = name or str(source), handle.read(16)
    try:
        fmt = format_by_content(head, HDR_MAGICS)
        if fmt == "exr":
            with decoding("the OpenEXR file"):
                pixels, attributes = _read_exr(source, max_pixels)
        elif fmt == "hdr":
            data = source if isinstance(source, bytes) else source.read_bytes()
            pixels, attributes = _read_radiance(data, max_pixels)
        else:
            raise UnsupportedFormatError(_not_hdr(head))
        values, clipped = validate_irradiance(pixels, clip_negative=clip_negative)
    except McamError as exc:
        raise type(exc)(f"{label}: {exc.message}") from None
    return HdrImage(pixels=values, attributes=attributes, negatives_clipped=clipped)


def _not_hdr(head: bytes) -> str:
    """Why a file whose leading bytes are ``head`` is refused as an HDR image, and what
    to do: a wrapped frame's file (PNG, TIFF, npy) is pointed to the reconstructions."""
    fmt = format_by_content(head, FRAME_MAGICS)
    if fmt is None:
        return "not an OpenEXR or Radiance HDR (.hdr, .pic) image; convert it to OpenEXR"
    return (
        f"a {fmt.upper()} file, not an OpenEXR or Radiance HDR (.hdr, .pic) image: if it is "
        "a wrapped frame, mcam reconstruct or POST /v1/reconstructions decodes it; else "
        "convert it to OpenEXR"
    )


def _exr_text(value: str) -> str:
    """``value`` as an EXR string attribute (UTF-8) can hold it: a byte of a file name
    that is not UTF-8 (a surrogate escape, as ``os.fsdecode`` gives) becomes ``\\xff``,
    any other lone surrogate ``\\ud800``."""
    try:
        raw = value.encode("utf-8", "surrogateescape")
    except UnicodeEncodeError:  # a surrogate that escapes no byte
        raw = value.encode("utf-8", "backslashreplace")
    return raw.decode("utf-8", "backslashreplace")


def encode_exr(
    pixels: NDArray[np.floating],
    attributes: dict[str, str] | None = None,
    *,
    half: bool = False,
    compression: str = DEFAULT_EXR_COMPRESSION,
) -> bytes:
    """An OpenEXR file (float32 or half) of ``H x W`` (channel Y) or ``H x W x 3`` (R,G,B),
    compressed as one of :data:`EXR_COMPRESSIONS`.

    ``attributes`` become string header attributes, after the standard ``capDate``
    (local time, ``YYYY:MM:DD HH:MM:SS``) and ``comments``, which they may replace;
    text UTF-8 cannot hold is escaped (:func:`_exr_text`).
    Raises :class:`OutputOverflowError` when a value does not fit the pixel type.
    """
    if compression not in EXR_COMPRESSIONS:
        raise InvalidInputError(
            f"unknown EXR compression {compression!r}; choose one of: "
            f"{', '.join(EXR_COMPRESSIONS)}"
        )
    arr = np.asarray(pixels, dtype=np.float64)
    if arr.ndim == 3 and arr.shape[2] == 1:
        arr = arr[:, :, 0]
    if arr.size == 0 or not (arr.ndim == 2 or (arr.ndim == 3 and arr.shape[2] == 3)):
        raise InvalidInputError(
            f"an HDR image is a non-empty H x W or H x W x 3 array, got shape {arr.shape}"
        )
    dtype = np.float16 if half else np.float32
    ensure_fits(arr, dtype, "HDR image")
    values = arr.astype(dtype)
    if values.ndim == 2:
        channels = {"Y": values}
    else:
        channels = {name: np.ascontiguousarray(values[:, :, i]) for i, name in enumerate("RGB")}
    header: dict[str, Any] = {
        "compression": EXR_COMPRESSIONS[compression],
        "type": OpenEXR.scanlineimage,
        "capDate": time.strftime("%Y:%m:%d %H:%M:%S"),
        "comments": "written by MantissaCam",
    }
    header.update({key: _exr_text(value) for key, value in (attributes or {}).items()})
    buffer = io.BytesIO()
    OpenEXR.File(header, channels).write(buffer)
    return buffer.getvalue()


def write_exr(
    path: str | os.PathLike[str],
    pixels: NDArray[np.floating],
    attributes: dict[str, str] | None = None,
    *,
    half: bool = False,
    compression: str = DEFAULT_EXR_COMPRESSION,
) -> None:
    """Write :func:`encode_exr`'s bytes to ``path``."""
    Path(path).write_bytes(encode_exr(pixels, attributes, half=half, compression=compression))
