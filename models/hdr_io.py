"""HDR image files: read OpenEXR (single- and multi-part) and Radiance RGBE, write OpenEXR.

Pixels are scene-referred linear values (float64 in memory), ``H x W`` (EXR
channel ``Y``) or ``H x W x 3`` (``R``, ``G``, ``B``). Every image read is checked
with :func:`models.formation.validate_irradiance`: NaN and inf are rejected,
negatives are rejected unless the caller asks to clip them (lossy EXR
compression leaves some), and the clipped count is reported.

The Radiance reader is :mod:`models.radiance`.
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

from models.errors import InvalidInputError, UnsupportedFormatError, naming
from models.exr_chunks import missing_chunks
from models.exr_limits import EXR_HEAD_BYTES, check_exr_headers, check_exr_size, part_size
from models.exr_parts import check_flat, image_part
from models.file_magic import FRAME_MAGICS, HDR_MAGICS, format_by_content
from models.formation import validate_irradiance
from models.frames import check_pixel_count, decoding
from models.output_range import ensure_fits, ensure_nonzero_kept
from models.radiance import read_radiance

_EXR_TRUNCATED = "the OpenEXR pixel data is truncated or corrupt; send the complete file"
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


def read_hdr(
    source: str | os.PathLike[str] | bytes,
    *,
    clip_negative: bool = False,
    max_pixels: int | None = None,
    name: str = "",
) -> HdrImage:
    """Read an OpenEXR or Radiance (.hdr/.pic) image from a path or bytes; format by magic.
    A path that is not a regular file (a pipe) is read whole first, once.

    ``name`` labels error messages (defaults to the path). Raises
    :class:`UnsupportedFormatError`, :class:`ImageTooLargeError` or
    :class:`InvalidInputError` (truncated, corrupt, NaN/inf/negative pixels).
    """
    if not isinstance(source, bytes) and not Path(source).is_file():
        # A pipe (``<(gunzip -c s.exr.gz)``, a FIFO) yields its bytes once; a path is
        # opened again below (leading bytes, headers, decoder), each open reading on.
        name, source = name or str(source), Path(source).read_bytes()
    if isinstance(source, bytes):
        label, head = name or "the HDR image", source[:16]
    else:
        source = Path(source)
        with source.open("rb") as handle:
            label, head = name or str(source), handle.read(16)
    with naming(label):
        fmt = format_by_content(head, HDR_MAGICS)
        if fmt == "exr":
            with decoding("the OpenEXR file"):
                pixels, attributes = _read_exr(source, max_pixels)
        elif fmt == "hdr":
            data = source if isinstance(source, bytes) else source.read_bytes()
            pixels, attributes = read_radiance(data, max_pixels)
        else:
            raise UnsupportedFormatError(_not_hdr(head))
        values, clipped = validate_irradiance(pixels, clip_negative=clip_negative)
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
    scene_gain: float | None = None,
) -> bytes:
    """An OpenEXR file (float32 or half) of ``H x W`` (channel Y) or ``H x W x 3`` (R,G,B),
    compressed as one of :data:`EXR_COMPRESSIONS`.

    ``attributes`` become string header attributes, after the standard ``capDate``
    (local time, ``YYYY:MM:DD HH:MM:SS``) and ``comments``, which they may replace;
    text UTF-8 cannot hold is escaped (:func:`_exr_text`).
    Raises :class:`OutputOverflowError` when a value does not fit the pixel type and
    :class:`OutputUnderflowError` when a nonzero one would be stored as 0; their remedy
    names ``scene_gain``, the gain the values were divided by (None: not scene-referred).
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
    ensure_fits(arr, dtype, "HDR image", scene_gain)
    ensure_nonzero_kept(np.asarray(pixels), dtype, "HDR image", scene_gain)
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
    scene_gain: float | None = None,
) -> None:
    """Write :func:`encode_exr`'s bytes to ``path``."""
    data = encode_exr(
        pixels, attributes, half=half, compression=compression, scene_gain=scene_gain
    )
    Path(path).write_bytes(data)
