"""Wrapped videos: a sequence of frames of sensor codes (DN) with their parameters.

Formats
-------
- ``tiff``: a multi-page TIFF, one frame per page (``H x W`` or ``H x W x C``);
  thumbnails and transparency masks (NewSubfileType bits 0 and 2, a page per frame or
  more) are not frames and are skipped (:mod:`models.tiff_pages`); the
  parameters as JSON in the first page's ImageDescription (as :mod:`models.frames`
  writes it). A later page storing parameters of its own must store the same (as
  zipped frames must). A page that is not read (its compression, sample size or
  photometric interpretation: :func:`models.tiff_pages.check_page_format`) is refused
  as such before it is compared with the first. A lone page of separate colour
  planes that tifffile described as its array (``{"shape": [3, H, W]}``) is refused:
  ``tifffile.imwrite`` stores a stack of 3 or 4 grey frames so; so is an ImageJ
  hyperstack of two axes or more (frames and channels or slices), whose pages
  interleave them.
- ``npy``: one array ``T x H x W`` or ``T x H x W x C`` (booleans read as codes 0 and
  1); parameters from the caller.
  A ``T x H x W`` array whose last axis could be channels (1 or 3) is refused as one
  frame ``H x W x C``: frames 1 or 3 pixels wide are sent as ``T x H x 1 x 1`` or
  ``T x H x 3 x 1``.
- ``zip``: a zip of PNG frames (:mod:`models.frames` PNGs), in natural file-name order
  regardless of case (``frame_2.png`` before ``frame_10.png``, ``frame_1.png`` before
  ``Frame_2.png``); parameters from the first frame's text chunk (a later frame storing
  none has the first frame's; one storing its own must store the same, as TIFF pages
  must). Folders and macOS metadata (``__MACOSX/``, resource forks ``._name.png``) are
  ignored; other files that are not ``.png`` are left out, with a warning naming them.

The frame count (``max_frames``), the pixels per frame (``max_pixels``) and the code
values of the whole video (``max_samples``: frames x pixels x channels) are checked
from headers before pixel data is decoded, and no zip entry is inflated beyond what a
PNG frame of ``max_pixels`` can hold (a few MB of zip can declare gigabytes).
Caller overrides (flags, form fields) win over stored parameters, as for single
frames.
"""

from __future__ import annotations

import io
import json
import logging
import os
import re
import unicodedata
import zipfile
from collections import Counter
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
import tifffile
from numpy.typing import NDArray

from models.decoders.base import FRAME_CHANNELS, check_frame_shape
from models.errors import (
    ImageTooLargeError,
    InvalidInputError,
    McamError,
    UnsupportedFormatError,
    echo,
)
from models.file_magic import (
    FRAME_MAGICS,
    HDR_MAGICS,
    PNG_SIGNATURE,
    VIDEO_MAGICS,
    check_signature,
    content_first,
    format_by_content,
    named_else_shown,
    refuse_empty,
)
from models.formation import SensorParams, validate_codes
from models.frame_params import merge_params
from models.frames import (
    WrappedFrame,
    check_pixel_count,
    decode_frame_codes,
    decoding,
    eight_bit_warning,
    not_a_frame,
)
from models.npy_files import npy_codes, npy_shape
from models.stored_params import StoredParams, tiff_params
from models.tiff_pages import check_page_format, open_tiff, page_codes, page_shape
from worker.zip_directory import central_entries

VIDEO_FORMATS: tuple[str, ...] = ("tiff", "npy", "zip")
#: File-name suffixes (and format names) of wrapped videos and the format each names.
VIDEO_ALIASES = {"tif": "tiff", "tiff": "tiff", "npy": "npy", "zip": "zip"}
#: Bytes inflated per read of a zip entry (bounds the memory one read can take).
INFLATE_CHUNK = 1 << 20
#: Entries a zip of frames may hold besides a PNG and a macOS resource fork per frame
#: (its folders, ``__MACOSX/``, notes): with none, a clip of the most frames a video
#: takes, zipped on macOS, was refused.
ZIP_OTHER_ENTRIES = 64
#: Most names of left-out zip entries a warning lists.
LISTED_ENTRIES = 5

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class VideoLimits:
    """What a wrapped video may hold (None: no limit): ``pixels`` per frame, ``frames``,
    and ``samples``, its code values in all (frames x pixels x channels)."""

    pixels: int | None = None
    frames: int | None = None
    samples: int | None = None


@dataclass(frozen=True)
class WrappedVideo:
    """Codes ``T x H x W`` (or ``T x H x W x C``, DN, the params' dtype) and their params."""

    codes: NDArray[np.unsignedinteger]
    params: SensorParams
    #: What reading the file noticed that the sender should know (as a frame's).
    warnings: tuple[str, ...] = ()

    @property
    def frames(self) -> int:
        """Number of frames T."""
        return int(self.codes.shape[0])


def video_format(name: str | os.PathLike[str]) -> str:
    """The video format (one of :data:`VIDEO_FORMATS`) of a file name, suffix or format name."""
    key = str(name).lower().rsplit(".", 1)[-1]
    if key not in VIDEO_ALIASES:
        raise UnsupportedFormatError(
            f"unsupported wrapped-video format {str(name)!r}; use a multi-page .tiff, "
            "a .npy of shape T x H x W[x C], or a .zip of PNG frames"
        )
    return VIDEO_ALIASES[key]


def check_frame_count(count: int, max_frames: int | None) -> None:
    """Refuse an empty video or one longer than ``max_frames``."""
    if count < 1:
        raise InvalidInputError("the video has no frames; send at least one frame")
    if max_frames is not None and count > max_frames:
        raise ImageTooLargeError(
            f"the video has {count} frames, above the limit of {max_frames}; send a shorter "
            "clip or raise the limit (MCAM_MAX_VIDEO_FRAMES)"
        )


def check_sample_count(frames: int, frame_shape: tuple[int, ...], max_samples: int | None) -> None:
    """Refuse a video whose code values (``frames`` x the product of ``frame_shape``)
    exceed ``max_samples``."""
    samples = frames * int(np.prod(frame_shape, dtype=np.int64))
    if max_samples is not None and samples > max_samples:
        shape = " x ".join(str(n) for n in (frames, *frame_shape))
        raise ImageTooLargeError(
            f"the video holds {samples} code values ({shape}), above the limit of "
            f"{max_samples}; send fewer or smaller frames, or raise the limit "
            "(MCAM_MAX_VIDEO_SAMPLES)"
        )


def png_entry_limit(max_pixels: int | None) -> int | None:
    """Most bytes a zip entry may inflate to: a 16-bit grayscale PNG frame of
    ``max_pixels`` stored without compression is under ``2 * max_pixels`` plus row
    filters and chunk headers; twice that and 1 MiB leaves room for any real PNG."""
    return None if max_pixels is None else 4 * max_pixels + 2**20


def _read_tiff(
    data: bytes, overrides: dict[str, Any] | None, limits: VideoLimits
) -> tuple[NDArray[Any], StoredParams]:
    with open_tiff(data, limits.frames) as (_, pages):
        count = len(pages)
        if limits.frames is not None and count > limits.frames:
            raise ImageTooLargeError(
                f"the TIFF holds more than {limits.frames} pages (one frame each); send a "
                "shorter clip or raise the limit (MCAM_MAX_VIDEO_FRAMES)"
            )
        check_frame_count(count, limits.frames)
        first = pages[0]
        if count == 1:
            _check_not_a_stack_of_planes(first)
        _check_not_a_hyperstack(first.description, count)
        check_pixel_count(int(first.imagewidth), int(first.imagelength), limits.pixels)
        check_sample_count(count, page_shape(first), limits.samples)
        stored = tiff_params(first.description)
        frames = []
        for page in pages:
            check_page_format(page)  # its own format first, then its likeness to page 0
            if frames:
                _check_page(page, len(frames), first, stored, overrides)
            frames.append(page_codes(page))
        return np.stack(frames), stored


def _check_not_a_stack_of_planes(page: tifffile.TiffPage) -> None:
    """Refuse the one page of a TIFF video when it holds separate colour planes whose
    description is tifffile's own of an array of that shape (``{"shape": [3, H, W]}``):
    ``tifffile.imwrite(path, frames)`` stores a stack of 3 (or 4) grey frames so, as
    RGB (RGBA), and 3 frames became one colour frame without a word."""
    if page.planarconfig != tifffile.PLANARCONFIG.SEPARATE or page.samplesperpixel < 2:
        return
    try:
        described = json.loads(page.description or "null")
    except ValueError:
        return
    shape = [int(n) for n in page.shape]
    if len(shape) != 3 or not isinstance(described, dict) or described.get("shape") != shape:
        return
    planes, height, width = shape
    raise InvalidInputError(
        f"the TIFF holds one page of {planes} planes ({planes} x {height} x {width}), as "
        f"tifffile.imwrite stores an array of {planes} grey frames unless told otherwise: "
        "write the frames as pages, tifffile.imwrite(path, frames, "
        "photometric='minisblack'); a single colour frame goes to POST /v1/reconstructions "
        "(mcam reconstruct)"
    )


#: The axes of an ImageJ hyperstack its description counts, as they are named there.
IMAGEJ_AXES = ("frames", "channels", "slices")


def _check_not_a_hyperstack(description: str | None, pages: int) -> None:
    """Refuse a TIFF (of ``pages`` pages) that ImageJ's description (``ImageJ=...``,
    page 0) declares a hyperstack of two axes or more (frames and channels, or slices):
    each channel or slice is a page of its own, and 4 colour frames of 3 channels were
    read as a grey video of 12 frames. A stack of one axis, whatever ImageJ calls it,
    is a page per frame."""
    if not description or not description.startswith("ImageJ="):
        return
    sizes: dict[str, int] = {}
    for line in description.splitlines():
        name, _, value = line.partition("=")
        if name in IMAGEJ_AXES and value.strip().isdecimal() and int(value) > 1:
            sizes[name] = int(value)
    if len(sizes) < 2:
        return
    axes = " x ".join(f"{sizes[name]} {name}" for name in IMAGEJ_AXES if name in sizes)
    raise InvalidInputError(
        f"the TIFF is an ImageJ hyperstack of {axes}: its {pages} pages interleave them, "
        "and a TIFF video is one page per frame: save a page per time point (a colour "
        "frame's channels as its RGB samples, e.g. tifffile.imwrite(path, frames, "
        "photometric='rgb') of frames T x H x W x 3), or keep one channel and one slice"
    )


def _check_page(
    page: tifffile.TiffPage,
    index: int,
    first: tifffile.TiffPage,
    stored: StoredParams,
    overrides: dict[str, Any] | None,
) -> None:
    """Refuse page ``index`` when its size, sample type or sensor parameters (its own
    with ``overrides``; a page storing none has the first page's) differ from the
    first page's (``stored``)."""
    differences = []
    if page_shape(page) != page_shape(first):
        differences.append(f"size ({_size(page_shape(page))} against {_size(page_shape(first))})")
    if page.dtype != first.dtype:
        differences.append(f"sample type ({page.dtype} against {first.dtype})")
    own = tiff_params(page.description)
    if own and own != stored:
        differences += merge_params(stored, overrides).differences(merge_params(own, overrides))
    if differences:
        raise _frame_differs(f"page {index}", "page 0", differences)


def _check_npy_shape(shape: tuple[int, ...]) -> None:
    """Refuse an npy array that is not T x H x W[x C], or whose T x H x W reads as one
    frame H x W x C (a last axis of 1 or 3 channels): taken for a video, one colour
    frame became H frames 3 pixels wide."""
    if len(shape) == 2 or (len(shape) == 3 and shape[2] in FRAME_CHANNELS):
        raise _one_frame(shape)
    if len(shape) not in (3, 4):
        raise InvalidInputError(
            f"a wrapped video is an array T x H x W or T x H x W x C, got shape {shape}; "
            "save the frames stacked as one array T x H x W (grey) or T x H x W x 3 (colour)"
        )


def _one_frame(shape: tuple[int, ...]) -> InvalidInputError:
    """The error for an npy array of ``shape`` that reads as one frame, H x W or
    H x W x C, saying where to send it, how to shape a one-frame video, and how to
    shape a video of frames as wide as C (1 or 3 pixels: a line sensor's clip)."""
    one = " x ".join(str(side) for side in (1, *shape))
    if len(shape) == 2:
        layout, thin = "(H x W)", ""
    else:
        height, width, channels = shape
        layout = f"(H x W x {channels}), not a video of {height} frames {width} x {channels} px"
        thin = (
            f"; a video of frames {channels} pixel{'s' if channels > 1 else ''} wide is "
            f"T x H x {channels} x 1 (array[..., None])"
        )
    return InvalidInputError(
        f"the array of shape {shape} reads as one frame {layout}: send a frame to POST "
        f"/v1/reconstructions (mcam reconstruct), or a video of that one frame as {one} "
        f"(array[None]){thin}"
    )


def _read_npy(data: bytes, limits: VideoLimits) -> tuple[NDArray[Any], dict[str, Any]]:
    """The codes of an npy video, its shape checked from the header first; booleans (a
    1-bit video saved as such) as 0 and 1, as npy frames and 1-bit TIFF pages are read."""
    shape = npy_shape(data)
    _check_npy_shape(shape)
    check_frame_count(shape[0], limits.frames)
    check_pixel_count(shape[2], shape[1], limits.pixels)
    check_sample_count(shape[0], shape[1:], limits.samples)
    return npy_codes(data), {}


def _natural_key(name: str) -> tuple[list[Any], str]:
    """Sort key putting ``frame_2`` before ``frame_10`` and ``frame_1`` before
    ``Frame_2``: runs of decimal digits (what ``\\d`` matches) by their value
    (:func:`_number_key`), the rest regardless of case (``str.casefold``); names equal
    that way keep the order of their code points. ``str.isdigit`` also takes
    superscripts (``²``), which are not decimal digits."""
    parts = re.split(r"(\d+)", name)
    return [_number_key(part) if part.isdecimal() else part.casefold() for part in parts], name


def _number_key(digits: str) -> tuple[int, str]:
    """A key ordering runs of decimal digits (of any script) by their value: the count
    and the ASCII digits left once leading zeros go. ``int`` refuses runs of more than
    4300 digits, and a zip whose entry's name held one was called corrupt."""
    plain = "".join(str(unicodedata.decimal(digit)) for digit in digits).lstrip("0")
    return len(plain), plain


def _zip_entry_limit(max_frames: int) -> int:
    """Most entries a zip of at most ``max_frames`` PNG frames may hold, counted from its
    directory before :mod:`zipfile` reads it: a macOS resource fork per frame, and
    :data:`ZIP_OTHER_ENTRIES` folders and notes."""
    return 2 * max_frames + ZIP_OTHER_ENTRIES


def _read_zip(
    data: bytes, overrides: dict[str, Any] | None, limits: VideoLimits
) -> WrappedVideo:
    if limits.frames is not None:
        most = _zip_entry_limit(limits.frames)
        entries = central_entries(data, most)
        if entries is not None and entries > most:
            raise ImageTooLargeError(
                f"the zip holds more than {most} entries; a video takes at most "
                f"{limits.frames} frames (one PNG each): send fewer frames, without other files"
            )
    with zipfile.ZipFile(io.BytesIO(data)) as archive:
        files = [info for info in archive.infolist() if not _zip_metadata(info)]
        entries = sorted(
            (info for info in files if _png_name(info)),
            key=lambda info: _natural_key(info.filename),
        )
        if not entries:
            raise _no_png_frame([info.filename for info in files])
        _check_names_once(entries)
        check_frame_count(len(entries), limits.frames)
        first = _zip_frame(archive, entries[0], overrides, limits, png_entry_limit(limits.pixels))
        check_sample_count(len(entries), first.codes.shape, limits.samples)
        most = frame_entry_limit(first.codes)
        frames = [first]
        for entry in entries[1:]:
            frame = _zip_frame(archive, entry, overrides, limits, most, first.params)
            differences = _frame_differences(frame, first)
            if differences:
                raise _frame_differs(entry.filename, entries[0].filename, differences)
            frames.append(frame)
    codes = np.stack([frame.codes for frame in frames])
    warnings = [w for frame in frames for w in frame.warnings]
    warnings.append(eight_bit_warning(codes, first.params))
    warnings.append(_left_out_warning([info.filename for info in files if not _png_name(info)]))
    return WrappedVideo(codes, first.params, tuple(dict.fromkeys(filter(None, warnings))))


def _check_names_once(entries: list[zipfile.ZipInfo]) -> None:
    """Refuse PNG ``entries`` of which two or more share a name: a file added again to a
    zip (Python's ``ZipFile(path, "a")``, some archivers' updates) is a second entry
    beside the first, not its replacement, and both were read as frames, where an unzip
    tool keeps one of them."""
    counts = Counter(entry.filename for entry in entries)
    repeated = [name for name, count in counts.items() if count > 1]
    if repeated:
        name = repeated[0]
        raise InvalidInputError(
            f"the zip holds {counts[name]} entries named {echo(name)}"
            f"{f' (and {len(repeated) - 1} more names repeated)' if len(repeated) > 1 else ''}: "
            "a frame added to a zip again is a second entry, not a replacement, and which "
            "one is the frame is unclear; zip the frames afresh, one entry per name"
        )


def _zip_metadata(entry: zipfile.ZipInfo) -> bool:
    """Whether a zip entry is no file of the sender's: a folder, or macOS metadata
    (``__MACOSX/``, ``._name`` resource forks)."""
    name = entry.filename
    return (
        entry.is_dir()
        or name.startswith("__MACOSX/")
        or name.rsplit("/", 1)[-1].startswith("._")
    )


def _png_name(entry: zipfile.ZipInfo) -> bool:
    """Whether a zip entry is named as a PNG frame."""
    return entry.filename.lower().endswith(".png")


def _left_out_warning(names: list[str]) -> str | None:
    """The warning, logged and returned for the job's ``warnings``, naming the files of
    a zip (``names``) that are not ``.png`` frames and so are not in the video (a frame
    saved as JPEG or TIFF was dropped without a word); None when there are none."""
    if not names:
        return None
    files = (
        "1 file of the zip that is not a .png frame"
        if len(names) == 1
        else f"{len(names)} files of the zip that are not .png frames"
    )
    warning = (
        f"left out of the video {files}: {_listed(names)}; if any is a frame, send it as a "
        "PNG (mcam simulate -o frame.png)"
    )
    logger.warning("%s", warning)
    return warning


def _listed(names: list[str]) -> str:
    """The first :data:`LISTED_ENTRIES` of ``names`` (each quoted, a long one cut short
    by :func:`models.errors.echo`: a zip entry's name may run to 64 KiB), and how many
    more."""
    more = f" and {len(names) - LISTED_ENTRIES} more" if len(names) > LISTED_ENTRIES else ""
    return ", ".join(echo(name) for name in names[:LISTED_ENTRIES]) + more


#: How to send frames saved in another array container, in an error message.
_SAVE_AS_NPY = "save the frames stacked as one array in a .npy file instead"


def _no_png_frame(names: list[str]) -> InvalidInputError:
    """The error for a zip of no ``.png`` frame, whose files are ``names``: what it
    holds, and for NumPy's ``.npz`` (a zip of ``.npy`` arrays) or PyTorch's
    ``torch.save`` file (a zip holding ``<name>/data.pkl``), what to send instead."""
    holds = f"its files: {_listed(names)}" if names else "no file"
    if names and all(name.lower().endswith(".npy") for name in names):
        remedy = (
            f"it is a NumPy .npz archive (np.savez): {_SAVE_AS_NPY} (np.save, T x H x W or "
            "T x H x W x 3)"
        )
    elif any(name.rsplit("/", 1)[-1] == "data.pkl" for name in names):
        remedy = (
            f"it is a PyTorch file (torch.save), whatever its name: {_SAVE_AS_NPY} "
            "(np.save(path, tensor.numpy()), T x H x W or T x H x W x 3)"
        )
    else:
        remedy = "a wrapped video as a zip is one PNG of codes per frame, named in frame order"
    return InvalidInputError(f"the zip holds no .png frame ({holds}); {remedy}")


def _frame_differences(frame: WrappedFrame, first: WrappedFrame) -> list[str]:
    """How a zip's ``frame`` differs from its ``first``: size, sample type as stored (an
    8-bit PNG among 16-bit ones holds codes of another scale) and sensor parameters."""
    differences = []
    if frame.codes.shape != first.codes.shape:
        differences.append(f"size ({_size(frame.codes.shape)} against {_size(first.codes.shape)})")
    if frame.sample_type != first.sample_type:
        differences.append(f"sample type ({frame.sample_type} against {first.sample_type})")
    return differences + first.params.differences(frame.params)


def _size(shape: tuple[int, ...]) -> str:
    """A frame's shape as ``H x W`` or ``H x W x C``."""
    return " x ".join(str(side) for side in shape)


def _frame_differs(frame: str, first: str, differences: list[str]) -> InvalidInputError:
    """The error for a video ``frame`` that differs from its ``first`` in ``differences``."""
    return InvalidInputError(
        f"{frame} differs from {first} in {', '.join(differences)}; all frames of a video "
        "share one size, sample type and set of sensor parameters (only the noise seed "
        "may differ)"
    )


def frame_entry_limit(codes: NDArray[Any]) -> int:
    """Most bytes a zip entry may inflate to once the first frame (``codes``, H x W[x C])
    is read: twice a PNG of that frame stored without compression (a filter byte per
    row, two bytes a sample at most) and 1 MiB. Without it each entry could inflate to
    :func:`png_entry_limit` (a valid 8 x 8 PNG followed by 65 MB of zeros, 100 times in
    a 6.7 MB upload, took the API 19 s)."""
    height, width = codes.shape[:2]
    samples = width * (codes.shape[2] if codes.ndim == 3 else 1)
    return 2 * height * (1 + 2 * samples) + 2**20


def _zip_frame(
    archive: zipfile.ZipFile,
    entry: zipfile.ZipInfo,
    overrides: dict[str, Any] | None,
    limits: VideoLimits,
    most: int | None,
    unstored: SensorParams | None = None,
) -> WrappedFrame:
    """One PNG frame of a zip, refused before inflating when its declared size is above
    ``most`` bytes (:func:`png_entry_limit`, then :func:`frame_entry_limit`), and
    inflated in chunks of at most :data:`INFLATE_CHUNK` bytes up to that size (see
    :func:`_inflate`). ``unstored``: its parameters if it stores none (the first
    frame's, for the frames after it)."""
    if most is not None and entry.file_size > most:
        raise ImageTooLargeError(
            f"{entry.filename} inflates to {entry.file_size} bytes, more than a PNG frame "
            f"can hold ({most}: at most {limits.pixels} pixels, the size of the first "
            "frame once it is read); send smaller frames, without data after the image"
        )
    try:
        _check_inflatable(entry)
        data = _inflate(archive, entry)
        _check_frame_entry(data)
        return decode_frame_codes(data, "png", overrides, limits.pixels, unstored)
    except McamError as exc:
        raise type(exc)(f"{entry.filename}: {exc.message}") from None


#: What a .png entry of a zip of frames holds, in an error message.
_ZIP_A_FRAME = (
    "the frame's whole PNG file in each .png entry of the zip, as written (mcam simulate "
    "-o frame.png; not converted to another format, renamed or cut short)"
)


def _check_frame_entry(data: bytes) -> None:
    """Refuse an inflated ``.png`` entry that is empty or of no frame format, saying what
    an entry holds: the frame reader called an empty entry "not a PNG image" and offered
    a single frame's other ways in (a .tiff or .npy file, raw codes over HTTP), which a
    zip of frames does not take. A file of another reader (an HDR image, a zip) is left
    to the frame reader, which says what it is and where it goes."""
    refuse_empty(len(data), "the entry")
    if not_a_frame(data) is None:
        check_signature(data, FRAME_MAGICS, "a PNG image", "frame", _ZIP_A_FRAME)


#: Compression methods inflated here, by number, with their names. :mod:`zipfile` also
#: reads bzip2 and LZMA, but inflates each read of their compressed bytes whole, past
#: the entry's declared size (796 bytes of bzip2 declaring a 200-byte PNG inflated 512
#: MiB at once): only Deflate stops at the size asked for.
ZIP_METHODS: dict[int, str] = {zipfile.ZIP_STORED: "stored", zipfile.ZIP_DEFLATED: "Deflate"}
#: The general-purpose flag of an encrypted zip entry.
ZIP_ENCRYPTED = 0x1


def _check_inflatable(entry: zipfile.ZipInfo) -> None:
    """Refuse an entry that is whole but is not inflated here (password-protected, or
    compressed with a method not in :data:`ZIP_METHODS`: Deflate64, bzip2, LZMA), saying
    how to zip the frames instead: zipfile's errors were reported as a truncated or
    corrupt file, and its bzip2 and LZMA inflate without bound."""
    how = "zip the frames without a password, stored or with Deflate (zip -r, or Python's zipfile)"
    if entry.flag_bits & ZIP_ENCRYPTED:
        raise UnsupportedFormatError(f"the entry is encrypted; {how}")
    if entry.compress_type not in ZIP_METHODS:
        raise UnsupportedFormatError(
            f"the entry is compressed with method {entry.compress_type}, which is "
            f"not read here (only {', '.join(ZIP_METHODS.values())}); {how}"
        )


def _inflate(archive: zipfile.ZipFile, entry: zipfile.ZipInfo) -> bytes:
    """The entry's bytes, inflated a chunk at a time. ``archive.read`` inflates as much
    as 2 GiB in one call before cutting to the declared size, so a 1 MB entry declaring
    211 bytes took the API to 2.2 GiB; chunked reads stop at the declared size."""
    with archive.open(entry) as stream:
        return b"".join(iter(lambda: stream.read(INFLATE_CHUNK), b""))


#: What a file of another reader's format is, and where it goes.
_NOT_VIDEOS = {
    "png": "a PNG image, one wrapped frame, not a video: decode it with mcam reconstruct or "
    "POST /v1/reconstructions, or send the clip's PNG frames together in one .zip",
    "exr": "an OpenEXR image (scene irradiance), not a wrapped video: make wrapped frames "
    "of it with mcam simulate or POST /v1/simulate",
    "hdr": "a Radiance HDR image (scene irradiance), not a wrapped video: make wrapped "
    "frames of it with mcam simulate or POST /v1/simulate",
}


def not_a_video(data: bytes) -> str | None:
    """What ``data`` is when it is a file another reader takes (a frame, an HDR image),
    and where to send it; None otherwise."""
    fmt = format_by_content(data, ((PNG_SIGNATURE, "png"), *HDR_MAGICS))
    return None if fmt is None else _NOT_VIDEOS[fmt]


#: What a file of each video format is, in an error message.
_FORMAT_NOUNS = {"tiff": "a TIFF video", "npy": "an npy file", "zip": "a zip of PNG frames"}
#: What to send instead of data of no video format.
_SEND_A_VIDEO = (
    "the wrapped video's file itself, as written (a multi-page .tiff/.tif, a T x H x W[x3] "
    ".npy or a .zip of PNG frames; not converted to another format, renamed or cut short)"
)


def decode_video(
    data: bytes,
    fmt: str,
    overrides: dict[str, Any] | None = None,
    limits: VideoLimits | None = None,
) -> WrappedVideo:
    """Decode a wrapped video's bytes; ``overrides`` fill in or replace stored params.

    ``fmt`` (a format name, suffix or file name) is the format unless the leading bytes
    show another video format: the content wins (see :mod:`models.file_magic`). Frames a
    decoder cannot take (not 1 or 3 channels, under 2 x 2 pixels when they may wrap) are
    refused here, before a job is queued."""
    fmt, warning = content_first(data, video_format(fmt), VIDEO_MAGICS)
    if (other := not_a_video(data)) is not None:
        raise UnsupportedFormatError(f"the file is {other}")
    check_signature(data, VIDEO_MAGICS, _FORMAT_NOUNS[fmt], "video", _SEND_A_VIDEO)
    limits = limits or VideoLimits()
    if fmt == "zip":
        with decoding("the ZIP video"):
            video = _read_zip(data, overrides, limits)
    else:
        with decoding(f"the {fmt.upper()} video"):
            if fmt == "tiff":
                codes, stored = _read_tiff(data, overrides, limits)
            else:
                codes, stored = _read_npy(data, limits)
        params = merge_params(stored, overrides)
        codes = validate_codes(codes, params.bits).astype(params.code_dtype, copy=False)
        eight_bit = eight_bit_warning(codes, params)
        video = WrappedVideo(codes, params, (eight_bit,) if eight_bit else ())
    check_frame_shape(video.codes[0], video.params)
    return video if warning is None else replace(video, warnings=(warning, *video.warnings))


def read_video(
    path: str | os.PathLike[str],
    overrides: dict[str, Any] | None = None,
    limits: VideoLimits | None = None,
) -> WrappedVideo:
    """Read a wrapped-video file (a pipe too); the format is its content's, else its
    suffix's (:func:`models.file_magic.named_else_shown`)."""
    data = Path(path).read_bytes()
    fmt = named_else_shown(str(path), data, VIDEO_MAGICS, video_format)
    return decode_video(data, fmt, overrides, limits)
