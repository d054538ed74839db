"""The leading bytes ("magic numbers") of the file formats the readers take.

A file's format is judged by its content first and by its name only when the content
shows none of the formats a reader takes: a PNG named ``.tiff`` is decoded as the PNG it
is (it was called a corrupt TIFF), with a warning naming both, logged and returned to
the caller (:func:`content_first`).
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Mapping
from typing import NamedTuple

from models.errors import InvalidInputError, UnsupportedFormatError

#: The eight bytes every PNG file starts with.
PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
#: Leading bytes of TIFF files: little- and big-endian, classic and BigTIFF.
TIFF_MAGICS: tuple[bytes, ...] = (b"II*\x00", b"MM\x00*", b"II+\x00", b"MM\x00+")
#: Leading bytes of NumPy ``.npy`` files.
NPY_MAGIC = b"\x93NUMPY"
#: Leading bytes of a zip archive (its first local file header).
ZIP_MAGIC = b"PK\x03\x04"
#: Leading bytes of a zip archive of no entries: its end record alone (Python's zipfile
#: writes one when nothing was added, as when the glob of the frames matched none).
EMPTY_ZIP_MAGIC = b"PK\x05\x06"
#: Leading bytes of OpenEXR files.
EXR_MAGIC = b"\x76\x2f\x31\x01"
#: Leading bytes of Radiance RGBE (.hdr, .pic) files.
RADIANCE_MAGICS: tuple[bytes, ...] = (b"#?RADIANCE", b"#?RGBE")

#: (leading bytes, format name) pairs.
Magics = tuple[tuple[bytes, str], ...]
#: Wrapped-frame formats (:mod:`models.frames`).
FRAME_MAGICS: Magics = (
    (PNG_SIGNATURE, "png"), *((magic, "tiff") for magic in TIFF_MAGICS), (NPY_MAGIC, "npy")
)
#: Wrapped-video formats (:mod:`worker.video_input`).
VIDEO_MAGICS: Magics = (
    *((magic, "tiff") for magic in TIFF_MAGICS),
    (NPY_MAGIC, "npy"),
    (ZIP_MAGIC, "zip"),
    (EMPTY_ZIP_MAGIC, "zip"),
)
#: HDR image formats (:mod:`models.hdr_io`).
HDR_MAGICS: Magics = ((EXR_MAGIC, "exr"), *((magic, "hdr") for magic in RADIANCE_MAGICS))

logger = logging.getLogger(__name__)


def format_by_content(data: bytes, magics: Magics) -> str | None:
    """The format of ``magics`` whose leading bytes ``data`` starts with; None if none."""
    return next((fmt for magic, fmt in magics if data.startswith(magic)), None)


def named_else_shown(name: str, data: bytes, magics: Magics, by_name: Callable[[str], str]) -> str:
    """The format ``by_name`` gives the file name ``name``, or, when it refuses the name
    (:class:`UnsupportedFormatError`: no suffix read here, as ``frame`` or a pipe's
    ``/dev/fd/63``), the one of ``magics`` that the file's ``data`` shows; its refusal
    stands when the data shows none. Such a file of a known format was refused by name."""
    try:
        return by_name(name)
    except UnsupportedFormatError:
        shown = format_by_content(data, magics)
        if shown is None:
            raise
        return shown


def named_format(name: str | None, aliases: Mapping[str, str]) -> str | None:
    """The format the suffix of the file name ``name`` names, by ``aliases`` (suffix ->
    format, lower case, no dot); None for no name, no suffix or one ``aliases`` lacks."""
    if not name or "." not in name:
        return None
    return aliases.get(name.rsplit(".", 1)[-1].lower())


def refuse_empty(size: int, what: str) -> None:
    """Refuse a file of ``size`` bytes that holds none (not yet written, or cut short
    to nothing), which the readers called a file of no known format: ``what`` names it
    ("the uploaded file", "the file clip.npy")."""
    if size == 0:
        raise InvalidInputError(f"{what} is empty; send the whole file")


def check_signature(data: bytes, magics: Magics, named: str, kind: str, send: str) -> None:
    """Refuse ``data`` whose leading bytes show none of the formats of ``magics`` (a JPEG
    or a text file named as one of them, a file cut short), which the readers called a
    truncated or corrupt file of the format its name gave. The message says it is not
    ``named`` (what the name promised, e.g. "a PNG image") nor any ``kind`` format read
    here, and to send ``send`` instead."""
    if format_by_content(data, magics) is None:
        raise InvalidInputError(
            f"the data is not {named} (bad or missing signature), nor any {kind} format "
            f"read here: send {send}"
        )


class Judged(NamedTuple):
    """The format to decode a file as, and the warning naming both formats when its
    name or declared format said another (None when they agree)."""

    format: str
    warning: str | None


def content_first(data: bytes, named: str, magics: Magics) -> Judged:
    """The format to decode ``data`` as: the one of ``magics`` its leading bytes show,
    else ``named`` (the format its file name or the caller gave). A disagreement is
    logged as a warning naming both, and returned for the caller to pass on (the API
    tells its client: a job's ``warnings``)."""
    content = format_by_content(data, magics)
    if content is None or content == named:
        return Judged(named, None)
    warning = (
        f"the file's content is {content.upper()} although its name or declared format "
        f"says {named.upper()}: decoding it as {content.upper()}; name or declare it "
        f"{content.upper()} to match"
    )
    logger.warning("%s", warning)
    return Judged(content, warning)
