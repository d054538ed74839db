"""TIFF pages of wrapped frames and videos, read strictly: the one TIFF reader of
:mod:`models.frames` (a frame: one page) and :mod:`worker.video_input` (a video: a page
per frame).

- tifffile reports some damage (a page offset past the end of a truncated file) only
  as a log warning and goes on with the pages before it; :func:`open_tiff` turns such
  a warning into :class:`TiffDamaged`, so half a video is refused, not decoded short.
  While any thread is in it, tifffile's logger has its own level (WARNING), so a
  global level (CRITICAL) cannot hide the warning, and does not propagate: the
  warning is raised, not logged.
- Only the compressions of :data:`ACCEPTED_COMPRESSIONS` are read: those tifffile
  decodes itself, without the optional ``imagecodecs`` package (which, installed,
  would bring decoders of its own that nothing here bounds). Any other (LZW, JPEG,
  Zstandard, ..., a code of no known compression) is refused by name
  (:func:`page_codes`), not reported as damage: tifffile claims Zstandard on Python
  before 3.14 and fails only when a strip is decoded ("No module named 'compression'").
- Pages that are not images are skipped: reduced-resolution ones (NewSubfileType bit 0:
  the thumbnails and pyramid levels cameras and editors add) and transparency masks
  (bit 2: the 1-bit mask of an image some editors write after it), a page with either
  bit or both. :func:`open_tiff` gives the full-resolution images, so a frame with its
  thumbnail or mask is one frame, a video's thumbnails and masks no frames.
- A page with a strip or tile not stored, or with tiles far larger than the page, is
  refused, and a compressed one is inflated with a bound: :mod:`models.tiff_segments`.
- Only samples of :data:`ACCEPTED_SAMPLE_BITS` bits are read: those tifffile unpacks
  itself. Others (a camera's 10-, 12- or 14-bit packed samples, 24 bits, sizes of no
  numpy type such as 0 or 33 bits) are refused by size (:func:`check_sample_bits`), not
  reported as damage ("requires the 'imagecodecs' package") or read as no samples.
- Pages whose samples are not grey or RGB values (palette indices, CMYK, YCbCr,
  L*a*b*, log-encoded luminance: :data:`NOT_CODES`) are refused by their photometric
  interpretation (:func:`check_photometric`): tifffile gives them as stored, and a
  palette frame's indices were decoded as codes.
- A grey page whose photometric interpretation is MinIsWhite (0: the largest value
  black, the smallest white) is inverted to the codes
  it stands for (:func:`_as_minisblack`): for unsigned integer samples, the page's
  largest value (``2^bits - 1``: 1, 255, 65535, ...) minus each stored one; tifffile
  gives them as stored, and a frame's codes came out as ``255 - code``. Signed and
  floating-point MinIsWhite samples, which codes are not stored as, are refused
  (:func:`check_photometric`): save them MinIsBlack.
- Separate-plane colour pages (``planarconfig=separate``, stored ``C x H x W``) are
  returned ``H x W x C``, as contiguous pages are.
- A page stored in more than :data:`MAX_TIFF_SEGMENTS` strips or tiles, of no rows or
  no columns, or a volume of slices (ImageDepth over 1) is refused by :func:`open_tiff`
  before any is decoded.
"""

from __future__ import annotations

import io
import itertools
import logging
import threading
from collections.abc import Iterable, Iterator
from contextlib import contextmanager
from typing import Any

import numpy as np
import tifffile
from numpy.typing import NDArray

from models.errors import ImageTooLargeError, InvalidInputError, UnsupportedFormatError
from models.tiff_segments import (
    INFLATERS,
    check_segment_sizes,
    check_segments_stored,
    inflated_once,
    separate_planes,
)

#: The most strips or tiles one page of a TIFF may be stored in: tifffile decodes them
#: one by one in Python (about 2.7 us and 250 bytes each: a 2 x 8,388,608 frame in
#: one-row strips, 8 million pointing at the same 2 bytes of a 32 MB file, took 22 s and
#: +2.2 GB). Every layout of a 4096 x 4096 frame fits: a row a strip (4096; 12,288 in
#: separate planes) or 16 x 16 tiles (65,536; 196,608). A page, not the file: a video of
#: 600 frames of 512 rows, a row a strip, is 307,200 strips; a video's strips are bounded
#: by its code values (``MCAM_MAX_VIDEO_SAMPLES``), at least one a strip.
MAX_TIFF_SEGMENTS = 1 << 18


class TiffDamaged(ValueError):
    """tifffile warned about the file's structure: it is truncated or corrupt."""


class _ThreadWarnings(logging.Handler):
    """Collects tifffile's warnings logged by one thread."""

    def __init__(self) -> None:
        super().__init__(logging.WARNING)
        self.thread = threading.get_ident()
        self.messages: list[str] = []

    def emit(self, record: logging.LogRecord) -> None:
        if record.thread == self.thread:
            self.messages.append(record.getMessage())

    def check(self) -> None:
        """Raise :class:`TiffDamaged` with the first warning, if any."""
        if self.messages:
            raise TiffDamaged(self.messages[0])


class _LoggerHold:
    """Holds tifffile's logger at WARNING or below, not propagating, while any thread
    reads a TIFF; the last one out restores its level and propagation."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._readers = 0
        self._saved = (logging.NOTSET, True)

    @contextmanager
    def held(self, logger: logging.Logger) -> Iterator[None]:
        """``logger`` reports warnings to its own handlers whatever the global level."""
        with self._lock:
            if self._readers == 0:
                self._saved = (logger.level, logger.propagate)
                if logger.level == logging.NOTSET or logger.level > logging.WARNING:
                    logger.setLevel(logging.WARNING)
                logger.propagate = False
            self._readers += 1
        try:
            yield
        finally:
            with self._lock:
                self._readers -= 1
                if self._readers == 0:
                    logger.setLevel(self._saved[0])
                    logger.propagate = self._saved[1]


_HOLD = _LoggerHold()


@contextmanager
def open_tiff(
    data: bytes, max_pages: int | None = None
) -> Iterator[tuple[tifffile.TiffFile, list[tifffile.TiffPage]]]:
    """The TIFF of ``data`` and its full-resolution pages (:func:`image_pages`), indexed
    now up to ``max_pages + 1`` of them (None: all; more than ``max_pages`` means "more",
    and the caller refuses the file: indexing 11 million empty pages of a 66 MB upload
    took 6 s and 420 MB). :class:`TiffDamaged` if tifffile warns while indexing or
    reading it (callers wrap that with :func:`models.frames.decoding`, which names the
    file); :class:`ImageTooLargeError` if a page indexed is stored in more than
    :data:`MAX_TIFF_SEGMENTS` strips or tiles; :class:`InvalidInputError` if one has no
    rows or no columns (:func:`_check_not_empty`) or is a volume
    (:func:`_check_not_a_volume`)."""
    logger = tifffile.logger()
    collector = _ThreadWarnings()
    logger.addHandler(collector)
    try:
        with _HOLD.held(logger), tifffile.TiffFile(io.BytesIO(data)) as tif:
            # Index the pages now: a truncated file warns here.
            most = None if max_pages is None else max_pages + 1
            pages = list(itertools.islice(image_pages(tif.pages), most))
            collector.check()
            for index, page in enumerate(pages):
                _check_segments(len(page.dataoffsets), index)
                _check_not_empty(page, index)
                _check_not_a_volume(page, index)
            yield tif, pages
        collector.check()
    finally:
        logger.removeHandler(collector)


#: The most pages that are not images (thumbnails, pyramid levels, transparency masks
#: and their reduced levels) a TIFF may hold per image and one more: a pyramid of a 4096
#: x 4096 frame halved down to one pixel has 12 levels, and with a mask of the frame and
#: of each level 25 such pages.
MAX_SKIPPED_PAGES = 32


def is_image(page: tifffile.TiffPage) -> bool:
    """Whether ``page`` is an image: NewSubfileType marks it neither reduced-resolution
    (bit 0: a thumbnail or pyramid level, a copy of an image) nor a transparency mask
    (bit 2: the 1-bit mask of an image)."""
    return not (page.is_reduced or page.is_mask)


def image_pages(pages: Iterable[tifffile.TiffPage]) -> Iterator[tifffile.TiffPage]:
    """``pages`` without those that are not images (:func:`is_image`: thumbnails,
    pyramid levels, transparency masks). Refused past :data:`MAX_SKIPPED_PAGES` of them
    per image and one more (:class:`ImageTooLargeError`: each is indexed), and when
    every page is one (:class:`InvalidInputError`)."""
    images = skipped = 0
    for page in pages:
        if is_image(page):
            images += 1
            yield page
            continue
        skipped += 1
        if skipped > MAX_SKIPPED_PAGES * (images + 1):
            raise ImageTooLargeError(
                f"the TIFF holds more than {MAX_SKIPPED_PAGES} reduced-resolution pages "
                "and transparency masks (thumbnails, pyramid levels, masks) per "
                "full-resolution image, which are not read; save it with fewer (a "
                "thumbnail and a mask an image, or none)"
            )
    if skipped and not images:
        raise InvalidInputError(
            f"the TIFF holds only reduced-resolution pages and transparency masks "
            f"({skipped}: thumbnails, masks), no full-resolution image as a page (a DNG or "
            "raw file stores it in a SubIFD): save the frame as a plain TIFF"
        )


def _check_segments(segments: int, index: int) -> None:
    """Refuse page ``index`` (from 0) stored in more than :data:`MAX_TIFF_SEGMENTS`
    strips or tiles."""
    if segments > MAX_TIFF_SEGMENTS:
        raise ImageTooLargeError(
            f"page {index} of the TIFF is stored in {segments} strips or tiles, more than "
            f"the {MAX_TIFF_SEGMENTS} read a page; re-save it in fewer, larger ones (more "
            "rows per strip, or larger tiles), as image tools do by default"
        )


def _check_not_empty(page: tifffile.TiffPage, index: int) -> None:
    """Refuse page ``index`` (from 0) of no rows or no columns, naming its size: such a
    frame was refused as "an array of shape (0,)", and such a page of a video as a size
    differing from its first page's."""
    rows, columns = int(page.imagelength), int(page.imagewidth)
    if rows and columns:
        return
    raise InvalidInputError(
        f"page {index} of the TIFF is {rows} x {columns} pixels (rows x columns): it holds "
        "none (tifffile writes an empty array so); send an image of at least one row and "
        "one column"
    )


def _check_not_a_volume(page: tifffile.TiffPage, index: int) -> None:
    """Refuse page ``index`` (from 0) that is a volume (ImageDepth over 1: slices of
    one size, ``D x H x W``): tifffile gives it as an array of three axes, and a volume
    of 3 slices 3 pixels wide was read as one RGB frame of its slices' rows."""
    depth = int(page.imagedepth)
    if depth <= 1:
        return
    raise InvalidInputError(
        f"page {index} of the TIFF is a volume of {depth} slices of {int(page.imagelength)} "
        f"x {int(page.imagewidth)} pixels (ImageDepth {depth}), and a frame is one image: "
        "save each slice as a page of its own (a video is a page per frame)"
    )


def page_shape(page: tifffile.TiffPage) -> tuple[int, ...]:
    """The shape :func:`page_codes` returns for ``page``: ``H x W`` or ``H x W x C``."""
    shape = tuple(int(n) for n in page.shape)
    return (*shape[1:], shape[0]) if separate_planes(page) else shape


#: The compressions :func:`page_codes` reads, by TIFF code, with their names in messages.
ACCEPTED_COMPRESSIONS: dict[int, str] = {
    1: "none",
    8: "deflate (zlib)",
    32946: "deflate (zlib)",
    32773: "PackBits",
    34925: "LZMA",
}


def check_compression(code: int) -> None:
    """Refuse (:class:`UnsupportedFormatError`) a TIFF compression ``code`` not in
    :data:`ACCEPTED_COMPRESSIONS`, naming it and those accepted."""
    if code in ACCEPTED_COMPRESSIONS:
        return
    try:
        name = f"{tifffile.COMPRESSION(code).name} ({code})"
    except ValueError:
        name = f"of unknown code {code}"
    accepted = ", ".join(dict.fromkeys(ACCEPTED_COMPRESSIONS.values()))
    raise UnsupportedFormatError(
        f"unsupported TIFF compression {name}; the compressions accepted are {accepted}: "
        "save the TIFF with one of them (deflate is the usual choice)"
    )


#: The sizes (bits) of the samples :func:`page_codes` reads: those tifffile unpacks
#: without ``imagecodecs`` (bits, bytes and words of 2, 4 and 8 bytes).
ACCEPTED_SAMPLE_BITS = (1, 8, 16, 32, 64)


def check_sample_bits(page: tifffile.TiffPage) -> None:
    """Refuse (:class:`UnsupportedFormatError`) ``page`` when its samples are not of
    :data:`ACCEPTED_SAMPLE_BITS` bits, or of a size and sample format of no numpy type,
    naming them: tifffile reported a 12-bit packed frame as needing the ``imagecodecs``
    package (refused as truncated or corrupt), and read one of 0 or 33 bits as no
    samples (refused as "an array of shape (0,)")."""
    bits = page.bitspersample
    if page.dtype is not None and bits in ACCEPTED_SAMPLE_BITS:
        return
    size = ", ".join(str(n) for n in bits) if isinstance(bits, tuple) else str(bits)
    try:
        kind = tifffile.SAMPLEFORMAT(int(page.sampleformat)).name
    except ValueError:
        kind = f"of unknown code {int(page.sampleformat)}"
    read = ", ".join(str(n) for n in ACCEPTED_SAMPLE_BITS)
    raise UnsupportedFormatError(
        f"the TIFF stores samples of {size} bits (sample format {kind}), which are not "
        f"read; the sample sizes read are {read} bits: save the image with 8- or 16-bit "
        "samples, its codes unchanged (a 10-, 12- or 14-bit code in a 16-bit sample)"
    )


_LAB = "L*a*b* colour values"
_LOG = "log-encoded luminance"
#: What the samples of a page of these photometric interpretations are: not sensor
#: codes as grey or RGB values, which tifffile gives as stored (not converted).
NOT_CODES: dict[int, str] = {
    tifffile.PHOTOMETRIC.PALETTE: "indices into its colour map (an indexed-colour image)",
    tifffile.PHOTOMETRIC.SEPARATED: "ink separations (CMYK)",
    tifffile.PHOTOMETRIC.YCBCR: "YCbCr values",
    tifffile.PHOTOMETRIC.CIELAB: _LAB,
    tifffile.PHOTOMETRIC.ICCLAB: _LAB,
    tifffile.PHOTOMETRIC.ITULAB: _LAB,
    tifffile.PHOTOMETRIC.LOGL: _LOG,
    tifffile.PHOTOMETRIC.LOGLUV: _LOG,
}


def check_photometric(page: tifffile.TiffPage) -> None:
    """Refuse (:class:`UnsupportedFormatError`) ``page`` when its photometric
    interpretation makes its samples something else than grey or RGB values
    (:data:`NOT_CODES`): a palette frame (an image saved as indexed colour) was decoded
    from its colour map's indices without a word; or when it is MinIsWhite with samples
    that are not unsigned integers (floats, signed), which :func:`_as_minisblack` does
    not invert."""
    photometric = int(page.photometric)
    unsigned = int(page.sampleformat) == tifffile.SAMPLEFORMAT.UINT
    if photometric == tifffile.PHOTOMETRIC.MINISWHITE and not unsigned:
        raise UnsupportedFormatError(
            f"the TIFF's samples are {np.dtype(page.dtype).name} stored MinIsWhite "
            "(photometric MINISWHITE: the largest value black), which is read only for "
            "unsigned integer samples (codes): save the image as grey MinIsBlack "
            "(photometric minisblack), its codes as the samples"
        )
    if photometric not in NOT_CODES:
        return
    raise UnsupportedFormatError(
        f"the TIFF's samples are {NOT_CODES[photometric]} (photometric "
        f"{tifffile.PHOTOMETRIC(photometric).name}), not sensor codes: save the image as "
        "grey (photometric minisblack), or RGB for a colour frame, its codes as the samples"
    )


def check_page_format(page: tifffile.TiffPage) -> None:
    """Refuse (:class:`UnsupportedFormatError`) ``page``, from its tags alone, when
    :func:`page_codes` does not read it: a compression not accepted
    (:func:`check_compression`), samples of a size not read (:func:`check_sample_bits`)
    or samples that are not grey or RGB values (:func:`check_photometric`). A video's
    pages are checked so before they are compared with its first: a 12-bit packed page
    1 was said to differ "in sample type (uint16 against uint8)"."""
    check_compression(int(page.compression))
    check_sample_bits(page)
    check_photometric(page)


def _as_minisblack(page: tifffile.TiffPage, samples: NDArray[Any]) -> NDArray[Any]:
    """``samples`` (unsigned integers, as :func:`page_codes` reads them from ``page``)
    as the codes they stand for: inverted from the page's largest value (``2^bits - 1``)
    when ``page`` is MinIsWhite, else unchanged."""
    if int(page.photometric) != tifffile.PHOTOMETRIC.MINISWHITE:
        return samples
    largest = samples.dtype.type((1 << int(page.bitspersample)) - 1)
    return largest - samples


def page_codes(page: tifffile.TiffPage) -> NDArray[Any]:
    """A page's samples, ``H x W`` or ``H x W x C`` (separate planes moved last);
    a 1-bit page's as uint8 0 and 1 (tifffile gives booleans); a MinIsWhite page's
    inverted to the codes they stand for (:func:`_as_minisblack`).

    Raises :class:`UnsupportedFormatError` for a page not read
    (:func:`check_page_format`); :class:`InvalidInputError` for a strip or tile not
    stored (:func:`check_segments_stored`)."""
    check_page_format(page)
    check_segment_sizes(page)
    check_segments_stored(page)
    inflate = INFLATERS.get(int(page.compression))
    codes = page.asarray() if inflate is None else inflated_once(page, inflate)
    if codes.dtype == np.bool_:
        codes = codes.astype(np.uint8)
    codes = _as_minisblack(page, codes)
    return np.moveaxis(codes, 0, -1) if separate_planes(page) else codes
