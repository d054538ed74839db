"""Wrapped-frame files: sensor codes (DN) plus their :class:`SensorParams`.

Formats
-------
- ``png``: grayscale 8- or 16-bit (1-, 2- and 4-bit PNGs of other software are read
  as stored too); codes stored as-is (never rescaled); the
  parameters as JSON in a ``tEXt`` chunk with keyword ``mantissacam``. Colour
  frames are refused: store them as TIFF.
- ``tiff``: ``H x W`` or ``H x W x C`` (decoders take C = 1 or 3: grey or RGB, no
  alpha); the parameters as JSON in the ImageDescription tag. One page of full
  resolution: reduced-resolution pages (thumbnails) and transparency masks
  (NewSubfileType bit 2, a 1-bit page some editors write after the image) are skipped.
  Written in the
  layout :func:`write_tiff_page` says (``H x W x 1`` as ``H x W``).
- ``npy``: the codes array only; parameters come from the caller.

Reading merges the stored parameters with overrides (:mod:`models.frame_params`). The
pixel count is checked from the header before any pixel data is decoded, so a small file
cannot expand into a huge image, and a PNG's compressed metadata (text, ICC profiles) is
inflated to 1 MiB at most (:mod:`models.png_chunks`). Winding maps (``W``, int64) are in
:mod:`models.winding_files`.
"""

from __future__ import annotations

import io
import logging
import os
import re
import struct
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, BinaryIO

import numpy as np
import tifffile
from numpy.typing import NDArray
from PIL import Image, PngImagePlugin, UnidentifiedImageError

from models.errors import (
    FormatCannotHoldError,
    ImageTooLargeError,
    InvalidInputError,
    McamError,
    UnsupportedFormatError,
    naming,
)
from models.file_magic import (
    FRAME_MAGICS,
    HDR_MAGICS,
    ZIP_MAGIC,
    check_signature,
    content_first,
    format_by_content,
    named_else_shown,
)
from models.formation import SensorParams, validate_codes
from models.frame_params import merge_params
from models.npy_files import npy_codes, npy_shape
from models.png_chunks import check_metadata
from models.stored_params import (
    StoredParams,
    parse_stored_params,
    tiff_params,
)
from models.tiff_pages import open_tiff, page_codes, page_shape

FRAME_FORMATS: tuple[str, ...] = ("png", "tiff", "npy")
#: PNG text-chunk keyword holding the parameters as JSON.
PNG_KEYWORD = "mantissacam"
#: File-name suffixes (and format names) of wrapped frames and the format each names.
FRAME_ALIASES = {"png": "png", "tif": "tiff", "tiff": "tiff", "npy": "npy"}
#: File-name suffixes of wrapped frames and winding maps.
FRAME_SUFFIXES: tuple[str, ...] = tuple(f".{name}" for name in FRAME_ALIASES)
#: Pillow modes of the grey PNGs read (of 1 to 16 bits a sample).
PNG_MODES = ("1", "L", "I;16", "I;16B", "I;16L", "I")
#: What to do with a PNG of a colour mode (RGB, RGBA).
_COLOUR_PNG_REMEDY = (
    "store a colour frame as TIFF, and a colour video as a multi-page TIFF (an RGB page "
    "per frame) or an npy T x H x W x 3, not as a zip of PNGs"
)
#: What a PNG of another Pillow mode not read holds, and what to do with it: a palette
#: image of grey codes (as PNG optimisers write one) was told to store colour as TIFF.
_PNG_MODE_REMEDIES = {
    "P": "its samples are indices into a palette (indexed colour), not sensor codes: save "
    "the frame as a grayscale PNG, its codes as the samples (a PNG optimiser may have "
    "turned it into a palette image)",
    "LA": "grey with an alpha channel: save the frame as a grayscale PNG without alpha",
}
#: Where a PNG's width and height are (big-endian 4-byte integers): after the signature
#: (8 bytes) and the IHDR chunk's length and type (8), its first fields.
_PNG_SIZE = slice(16, 24)
#: Where its bit depth per sample is: right after them.
_PNG_DEPTH_OFFSET = _PNG_SIZE.stop
logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class WrappedFrame:
    """A wrapped frame: codes in DN (uint8 or uint16, ``H x W`` or ``H x W x C``) and
    params; ``warnings``: what its reading noticed that the sender should know (a file
    named as another format than its content, codes that all fit in 8 bits although
    bits says more); ``sample_type``: the numpy type of the codes as the file stores
    them (``uint8``, ``uint16``), before they take the params' type ("" if not from a
    file)."""

    codes: NDArray[np.unsignedinteger]
    params: SensorParams
    warnings: tuple[str, ...] = ()
    sample_type: str = ""


def frame_format(name: str | os.PathLike[str]) -> str:
    """The frame format (one of :data:`FRAME_FORMATS`) of a file name, suffix or format name."""
    text = str(name).lower()
    key = text.rsplit(".", 1)[-1]
    if key not in FRAME_ALIASES:
        raise UnsupportedFormatError(
            f"unsupported wrapped-frame format {str(name)!r}; "
            "use one of: .png (grayscale), .tiff/.tif (grey or RGB), .npy"
        )
    return FRAME_ALIASES[key]


#: What a file of another reader's format is, and where it goes.
_NOT_FRAMES = {
    "exr": "an OpenEXR image (scene irradiance), not a wrapped frame: make a frame of it "
    "with mcam simulate or POST /v1/simulate",
    "hdr": "a Radiance HDR image (scene irradiance), not a wrapped frame: make a frame of it "
    "with mcam simulate or POST /v1/simulate",
    "zip": "a zip (of video frames?), not a wrapped frame: decode it as a video with "
    "mcam video or POST /v1/videos",
}


def not_a_frame(data: bytes) -> str | None:
    """What ``data`` is when it is a file another reader takes (an HDR image, a zip), and
    where to send it; None otherwise."""
    fmt = format_by_content(data, (*HDR_MAGICS, (ZIP_MAGIC, "zip")))
    return None if fmt is None else _NOT_FRAMES[fmt]


def check_pixel_count(width: int, height: int, max_pixels: int | None) -> None:
    """Raise :class:`ImageTooLargeError` when ``width * height`` exceeds ``max_pixels``."""
    if max_pixels is not None and width * height > max_pixels:
        raise ImageTooLargeError(
            f"the image is {width} x {height} = {width * height} pixels, above the limit of "
            f"{max_pixels}; send a smaller image or raise the pixel limit (MCAM_MAX_PIXELS)"
        )


def check_samples(shape: tuple[int, ...], max_pixels: int | None) -> None:
    """Raise :class:`ImageTooLargeError` when a frame of ``shape`` (from a file's header)
    holds more samples than an RGB frame of ``max_pixels``: a compressed TIFF of 1000
    samples a pixel decoded to gigabytes before its channels were looked at."""
    samples = int(np.prod(shape, dtype=np.int64))
    if max_pixels is not None and samples > 3 * max_pixels:
        raise ImageTooLargeError(
            f"the image's shape {shape} holds {samples} samples, more than an RGB frame of "
            f"at most {max_pixels} pixels ({3 * max_pixels}); a frame is grey or RGB"
        )


#: A Python object's memory address in a library's message (numpy's npy header errors
#: quote its parser's nodes): the server's memory layout is nobody's business.
_ADDRESS = re.compile(r" at 0x[0-9a-fA-F]+")


@contextmanager
def decoding(what: str) -> Iterator[None]:
    """Report a decoding library's failure on a truncated or corrupt file as bad input."""
    try:
        yield
    except McamError:
        raise
    except Exception as exc:  # PIL, tifffile, zlib and OpenEXR raise many types on bad data
        detail = _ADDRESS.sub("", " ".join(str(exc).split())) or type(exc).__name__
        raise InvalidInputError(
            f"{what} is truncated or corrupt ({detail}); send the complete, unmodified file"
        ) from None


def _check_layout(codes: NDArray[Any]) -> None:
    if codes.ndim not in (2, 3):
        raise InvalidInputError(
            f"a wrapped frame is H x W or H x W x C codes, got an array of shape {codes.shape}"
        )


def _storage_codes(codes: NDArray[Any], params: SensorParams | None) -> NDArray[Any]:
    """Validated codes in their storage dtype (the params' dtype, else uint8/uint16)."""
    arr = np.asarray(codes)
    _check_layout(arr)
    if params is not None:
        return validate_codes(arr, params.bits).astype(params.code_dtype, copy=False)
    validate_codes(arr, 16)
    return arr if arr.dtype == np.uint8 else arr.astype(np.uint16, copy=False)


def encode_frame(codes: NDArray[Any], params: SensorParams | None, fmt: str) -> bytes:
    """The bytes of a wrapped-frame file in format ``fmt`` (a name, suffix or file name)."""
    fmt = frame_format(fmt)
    arr = _storage_codes(codes, params)
    text = params.model_dump_json() if params is not None else None
    buffer = io.BytesIO()
    if fmt == "npy":
        np.save(buffer, arr, allow_pickle=False)
    elif fmt == "tiff":
        write_tiff_page(buffer, arr, text)
    else:
        if arr.ndim == 3 and arr.shape[2] == 1:
            arr = arr[:, :, 0]
        if arr.ndim == 3:
            raise FormatCannotHoldError(
                f"a PNG frame is grayscale (one channel) and this frame has {arr.shape[2]} "
                "channels: ask for TIFF or npy, which hold colour frames (a .tiff or .npy "
                "file, or format=tiff or format=npy over HTTP), or for luminance only "
                "(--gray, or gray=true over HTTP)"
            )
        info = PngImagePlugin.PngInfo()
        if text is not None:
            info.add_text(PNG_KEYWORD, text)
        Image.fromarray(arr).save(buffer, format="PNG", pnginfo=info)
    return buffer.getvalue()


def write_tiff_page(
    target: str | os.PathLike[str] | BinaryIO, arr: NDArray[Any], description: str | None
) -> None:
    """Write ``arr`` (``H x W`` or ``H x W x C``) as one deflate TIFF page, its layout
    said (tifffile guesses one from the shape, and will guess another): ``H x W x 3``
    RGB, other ``H x W x C`` grey with extra samples, contiguous; ``H x W x 1`` as the
    grey ``H x W`` page it is (a 4 x 3 x 1 array was guessed a 3 x 1 image of 4
    separate planes, and the contiguous layout asked for was refused with a
    ValueError)."""
    if arr.ndim == 3 and arr.shape[2] == 1:
        arr = arr[:, :, 0]
    tifffile.imwrite(
        target,
        arr,
        photometric="rgb" if arr.ndim == 3 and arr.shape[2] == 3 else "minisblack",
        planarconfig="contig" if arr.ndim == 3 else None,
        description=description,
        metadata=None,
        compression="zlib",
    )


def write_frame(
    path: str | os.PathLike[str], codes: NDArray[Any], params: SensorParams | None
) -> None:
    """Write a wrapped frame; the format follows the file's suffix."""
    Path(path).write_bytes(encode_frame(codes, params, frame_format(path)))


def _png_bomb_error(data: bytes, max_pixels: int | None) -> ImageTooLargeError:
    """The error for a PNG whose header declares more pixels than Pillow opens (twice
    ``Image.MAX_IMAGE_PIXELS``): its size against ``max_pixels`` when that is the lower
    limit, else against Pillow's. The size is the IHDR's, the first chunk."""
    width, height = struct.unpack(">II", data[_PNG_SIZE])
    try:
        check_pixel_count(width, height, max_pixels)
    except ImageTooLargeError as exc:
        return exc
    most = 2 * (Image.MAX_IMAGE_PIXELS or 0)
    return ImageTooLargeError(
        f"the PNG image is {width} x {height} = {width * height} pixels, above the "
        f"limit of {most} pixels the PNG reader decodes; send a smaller image (or split it "
        "into tiles)"
    )


def _read_png(data: bytes, max_pixels: int | None) -> tuple[NDArray[Any], StoredParams]:
    """The samples and stored parameters of a grey PNG frame, its compressed metadata
    bounded first (:func:`models.png_chunks.check_metadata`)."""
    check_metadata(data)
    try:
        image = Image.open(io.BytesIO(data), formats=["PNG"])
    except UnidentifiedImageError:
        # Only data with a PNG signature comes here (:func:`check_signature`).
        raise InvalidInputError(
            "the PNG's header is damaged (PNG signature, but no readable image header: "
            "zero or impossible size, bad chunk); send the frame as written"
        ) from None
    except Image.DecompressionBombError:
        raise _png_bomb_error(data, max_pixels) from None
    check_pixel_count(image.width, image.height, max_pixels)
    if image.mode not in PNG_MODES:
        remedy = _PNG_MODE_REMEDIES.get(image.mode, _COLOUR_PNG_REMEDY)
        raise UnsupportedFormatError(
            f"PNG frames are grayscale (1 to 16 bits), got PNG mode {image.mode}; {remedy}"
        )
    image.load()
    stored = parse_stored_params(image.text.get(PNG_KEYWORD), "PNG text chunk")
    return png_samples(image, data), stored


def png_samples(image: Image.Image, data: bytes) -> NDArray[Any]:
    """The samples of the grayscale PNG ``image`` (opened from ``data``) as stored.

    Pillow widens 1-, 2- and 4-bit samples to 8 bits: mode ``1`` as booleans, mode
    ``L`` scaled to 0..255 (a 2-bit 3 reads 255); this gives back the stored values."""
    pixels = np.asarray(image)
    depth = data[_PNG_DEPTH_OFFSET]
    if pixels.dtype == np.bool_:
        return pixels.astype(np.uint8)
    if depth < 8:
        return pixels // np.uint8(255 // ((1 << depth) - 1))
    return pixels


def _read_tiff(data: bytes, max_pixels: int | None) -> tuple[NDArray[Any], StoredParams]:
    with open_tiff(data, max_pages=1) as (_, pages):
        if len(pages) > 1:
            raise InvalidInputError(
                "the TIFF holds more than one page of full resolution (its thumbnails "
                "and masks aside) and a reconstruction takes one frame: send a single-page "
                "TIFF, or decode the sequence as a video (POST /v1/videos, mcam video)"
            )
        (page,) = pages
        check_pixel_count(int(page.imagewidth), int(page.imagelength), max_pixels)
        check_samples(page_shape(page), max_pixels)
        return page_codes(page), tiff_params(page.description)


def _read_npy(data: bytes, max_pixels: int | None) -> tuple[NDArray[Any], dict[str, Any]]:
    """The codes of an npy frame (:func:`models.npy_files.npy_codes`: booleans as 0 and 1)."""
    shape = npy_shape(data)
    if len(shape) not in (2, 3):
        raise InvalidInputError(
            f"a wrapped frame is H x W or H x W x C codes, got an array of shape {shape}"
        )
    check_pixel_count(shape[1], shape[0], max_pixels)
    return npy_codes(data), {}


_READERS = {"png": _read_png, "tiff": _read_tiff, "npy": _read_npy}

#: What a file of each frame format is, in an error message.
_FORMAT_NOUNS = {"png": "a PNG image", "tiff": "a TIFF image", "npy": "an npy file"}
#: What to send instead of data of no frame format.
_SEND_A_FRAME = (
    "the frame's file itself, as written (.png, .tiff/.tif or .npy; not converted to "
    "another format, renamed or cut short), or, over HTTP, raw codes with format=raw, "
    "width, height, bits and encoding"
)


def eight_bit_warning(codes: NDArray[Any], params: SensorParams) -> str | None:
    """The warning, logged and returned for the caller to pass on (a job's ``warnings``),
    when codes (DN) set to more than 8 bits all fit in 8: an 8-bit frame read with a
    wider bit depth decodes as almost black, without any error. None otherwise."""
    if params.bits <= 8 or int(codes.max()) >= 256:
        return None
    warning = (
        f"every code is below 256 although bits is {params.bits}: if the frame is 8-bit, "
        "give bits 8 (--bits 8, or the form field bits=8)"
    )
    logger.warning("%s", warning)
    return warning


def decode_frame(
    data: bytes,
    fmt: str,
    overrides: dict[str, Any] | None = None,
    max_pixels: int | None = None,
) -> WrappedFrame:
    """Decode a wrapped-frame file's bytes; ``overrides`` fill in or replace stored params.

    ``fmt`` (a format name, suffix or file name) is the format unless the leading bytes
    show another frame format: the content wins (see :mod:`models.file_magic`). An HDR
    image or a zip is refused with where to send it. Its warnings say when the content
    is not of ``fmt`` and when every code fits in 8 bits although ``bits`` is more."""
    frame = decode_frame_codes(data, fmt, overrides, max_pixels)
    eight_bit = eight_bit_warning(frame.codes, frame.params)
    return frame if eight_bit is None else replace(frame, warnings=(*frame.warnings, eight_bit))


def decode_frame_codes(
    data: bytes,
    fmt: str,
    overrides: dict[str, Any] | None = None,
    max_pixels: int | None = None,
    unstored: SensorParams | None = None,
) -> WrappedFrame:
    """:func:`decode_frame` without the 8-bit check, for a frame of a video whose codes
    are checked together (one dark frame of a 16-bit clip is not an 8-bit clip): its
    only warning is a content not of ``fmt``. ``unstored``: the parameters of a frame
    that stores none (a later frame of a video has its first frame's)."""
    fmt, warning = content_first(data, frame_format(fmt), FRAME_MAGICS)
    if (other := not_a_frame(data)) is not None:
        raise UnsupportedFormatError(f"the file is {other}")
    check_signature(data, FRAME_MAGICS, _FORMAT_NOUNS[fmt], "frame", _SEND_A_FRAME)
    with decoding(f"the {fmt.upper()} frame"):
        codes, stored = _READERS[fmt](data, max_pixels)
    _check_layout(codes)
    if unstored is not None and stored == {}:
        stored = unstored.model_dump()
    params = merge_params(stored, overrides)
    sample_type = codes.dtype.name
    codes = validate_codes(codes, params.bits).astype(params.code_dtype, copy=False)
    return WrappedFrame(codes, params, (warning,) if warning else (), sample_type)


def read_frame(
    path: str | os.PathLike[str],
    overrides: dict[str, Any] | None = None,
    max_pixels: int | None = None,
) -> WrappedFrame:
    """Read a wrapped-frame file (a pipe too); the format is its content's, else its
    suffix's. An error about the file's content names its path."""
    data = Path(path).read_bytes()
    fmt = named_else_shown(str(path), data, FRAME_MAGICS, frame_format)
    with naming(str(path)):
        return decode_frame(data, fmt, overrides, max_pixels)


def decode_raw(data: bytes, width: int, height: int, channels: int, bits: int) -> NDArray[Any]:
    """Codes from a raw upload: row-major ``H x W (x C)``, uint8 for bits <= 8, else uint16 LE."""
    if min(width, height, channels) < 1:
        raise InvalidInputError(
            f"raw frame size must be positive, got {width} x {height} x {channels}"
        )
    if not 1 <= bits <= 16:
        raise InvalidInputError(f"bits must be 1..16, got {bits}")
    dtype = np.dtype(np.uint8) if bits <= 8 else np.dtype("<u2")
    expected = width * height * channels * dtype.itemsize
    if len(data) != expected:
        raise InvalidInputError(
            f"a raw {width} x {height} x {channels} frame of {bits}-bit codes is {expected} bytes "
            f"({dtype.itemsize} per code), got {len(data)}; check the size and bit depth"
        )
    shape = (height, width) if channels == 1 else (height, width, channels)
    codes = np.frombuffer(data, dtype=dtype).reshape(shape)
    return validate_codes(codes.astype(dtype.newbyteorder("=")), bits)
