"""Tests of worker/video_input.py: multi-page TIFF, T x H x W[x3] .npy, zip of PNGs."""

from __future__ import annotations

import bz2
import io
import re
import struct
import tracemalloc
import zipfile
import zlib
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import tifffile
from PIL import Image

from models.errors import (
    ImageTooLargeError,
    InvalidInputError,
    MissingParameterError,
    UnsupportedFormatError,
)
from models.formation import SensorParams
from models.frames import encode_frame
from models.hdr_io import encode_exr
from tests.models.test_frames import miniswhite_tiff, write_mask
from tests.models.test_tiff_pages import with_short
from worker.video_input import (
    VideoLimits,
    decode_video,
    read_video,
    video_format,
)
from worker.zip_directory import central_entries

PARAMS = SensorParams(encoding="mantissa", alpha=2.0, bits=8)
FLAGS = {"encoding": "mantissa", "alpha": 2.0, "bits": 8}


def codes(frames: int = 4, channels: int | None = None) -> np.ndarray:
    shape = (frames, 6, 5) if channels is None else (frames, 6, 5, channels)
    return np.random.default_rng(frames).integers(0, 256, shape).astype(np.uint8)


def tiff_bytes(video: np.ndarray, params: SensorParams | None = PARAMS) -> bytes:
    buffer = io.BytesIO()
    rgb = video.ndim == 4
    tifffile.imwrite(
        buffer, video, photometric="rgb" if rgb else "minisblack",
        description=params.model_dump_json() if params else None, metadata=None,
    )
    return buffer.getvalue()


def npy_bytes(video: np.ndarray) -> bytes:
    buffer = io.BytesIO()
    np.save(buffer, video)
    return buffer.getvalue()


def zip_bytes(video: np.ndarray, names: list[str] | None = None) -> bytes:
    buffer = io.BytesIO()
    names = names or [f"frame_{t}.png" for t in range(len(video))]
    with zipfile.ZipFile(buffer, "w") as archive:
        archive.writestr("notes.txt", "not a frame")
        for name, frame in zip(names, video, strict=True):
            archive.writestr(name, encode_frame(frame, PARAMS, "png"))
    return buffer.getvalue()


@pytest.mark.parametrize("channels", [None, 3])
def test_multipage_tiff_round_trip(channels: int | None) -> None:
    video = codes(4, channels)
    result = decode_video(tiff_bytes(video), "tiff")
    np.testing.assert_array_equal(result.codes, video)
    assert result.params == PARAMS and result.frames == 4


def test_npy_round_trip_needs_parameters() -> None:
    video = codes(3, 3)
    with pytest.raises(MissingParameterError):
        decode_video(npy_bytes(video), "npy")
    result = decode_video(npy_bytes(video), "npy", FLAGS)
    np.testing.assert_array_equal(result.codes, video)


def test_an_npy_video_of_booleans_is_read_as_codes_0_and_1() -> None:
    """A 1-bit video saved as booleans was refused, "codes must be integers (uint8 or
    uint16), got dtype bool", though an npy frame of booleans and a 1-bit TIFF video
    are read as codes 0 and 1."""
    video = codes(3) > 127
    result = decode_video(npy_bytes(video), "npy", FLAGS | {"bits": 1})
    np.testing.assert_array_equal(result.codes, video.astype(np.uint8))
    assert result.codes.dtype == np.uint8

def test_zip_of_pngs_in_natural_order() -> None:
    video = codes(12)
    names = [f"clip/frame_{t}.png" for t in range(12)]
    result = decode_video(zip_bytes(video, names), "zip")
    np.testing.assert_array_equal(result.codes, video)
    assert result.params == PARAMS


def test_a_zip_of_colour_pngs_is_told_where_a_colour_video_goes() -> None:
    """It was told "store colour frames as TIFF", and a zip of TIFF frames was then
    refused as a zip of no .png frame: the remedy led nowhere a video is read."""
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w") as archive:
        for t, frame in enumerate(codes(2, 3)):
            png = io.BytesIO()
            Image.fromarray(frame).save(png, "PNG")
            archive.writestr(f"frame_{t}.png", png.getvalue())
    with pytest.raises(UnsupportedFormatError, match="mode RGB") as error:
        decode_video(buffer.getvalue(), "zip", FLAGS)
    assert "a colour video as a multi-page TIFF" in str(error.value)
    assert "T x H x W x 3" in str(error.value)

def test_a_zip_of_a_frame_added_twice_is_refused_naming_it() -> None:
    """A frame added again to a zip (ZipFile(path, "a")) is a second entry of that name;
    both were read, so the video held a frame more than the zip unzips to."""
    video = codes(3)
    buffer = io.BytesIO(zip_bytes(video[:2]))
    with pytest.warns(UserWarning, match="Duplicate name"):
        with zipfile.ZipFile(buffer, "a") as archive:
            archive.writestr("frame_1.png", encode_frame(video[2], PARAMS, "png"))
    with pytest.raises(InvalidInputError, match="holds 2 entries named 'frame_1.png'") as error:
        decode_video(buffer.getvalue(), "zip")
    assert "zip the frames afresh" in str(error.value)


def test_names_of_long_digit_runs_sort_by_value() -> None:
    """A name whose digits passed int's 4300 was "the ZIP video is truncated or corrupt
    (Exceeds the limit (4300 digits) for integer string conversion ...)"."""
    video = codes(3)
    long = "1" + "0" * 5000
    names = [f"frame_{long}.png", "frame_0002.png", f"frame_{long[:-1]}9.png"]
    result = decode_video(zip_bytes(video, names), "zip")
    np.testing.assert_array_equal(result.codes, video[[1, 0, 2]])


def test_frame_names_sort_regardless_of_case() -> None:
    """Names were sorted by code point: ``Frame_2.png`` (capital F) came before
    ``frame_1.png``, and ``FRAME_10.png`` before both."""
    video = codes(4)
    names = ["FRAME_10.png", "frame_3.png", "Frame_2.png", "frame_1.png"]
    result = decode_video(zip_bytes(video[[3, 2, 1, 0]], names), "zip")
    np.testing.assert_array_equal(result.codes, video)


def test_frame_names_with_other_digits_sort_by_their_decimal_numbers() -> None:
    """A superscript digit between digits (``frame_1²2.png``) made the sort key call
    ``int("²")``: the zip was refused as truncated or corrupt."""
    video = codes(3)
    names = ["frame_2.png", "frame_1²10.png", "frame_1²2.png"]
    result = decode_video(zip_bytes(video[::-1], names), "zip")
    np.testing.assert_array_equal(result.codes, video)


def test_macos_resource_forks_in_a_zip_are_not_frames() -> None:
    """Archivers on macOS store ``._name`` resource forks beside the files (outside
    ``__MACOSX/`` too): they are not PNGs and not frames."""
    video = codes(3)
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w") as archive:
        for t, frame in enumerate(video):
            archive.writestr(f"clip/frame_{t}.png", encode_frame(frame, PARAMS, "png"))
            archive.writestr(f"clip/._frame_{t}.png", b"\x00\x05\x16\x07 resource fork")
        archive.writestr("__MACOSX/clip/._frame_0.png", b"\x00\x05\x16\x07")
    np.testing.assert_array_equal(decode_video(buffer.getvalue(), "zip").codes, video)


def test_an_empty_zip_is_told_it_holds_no_frame() -> None:
    """A zip of no file (a glob that matched nothing) starts with its end record, not a
    file's header: it was refused as "not a zip of PNG frames (bad or missing
    signature)", to be sent uncut."""
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w"):
        pass
    with pytest.raises(InvalidInputError) as caught:
        decode_video(buffer.getvalue(), "clip.zip")
    assert caught.value.message.startswith("the zip holds no .png frame (no file)")


def test_files_of_a_zip_that_are_not_png_frames_are_named_in_a_warning() -> None:
    """A frame saved as JPEG among the PNGs was dropped from the video without a word."""
    video = codes(3)
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w") as archive:
        archive.writestr("clip/", b"")
        archive.writestr("clip/frame_0.png", encode_frame(video[0], PARAMS, "png"))
        archive.writestr("clip/frame_1.jpg", b"\xff\xd8\xff\xe0 a JPEG frame")
        archive.writestr("clip/frame_2.png", encode_frame(video[2], PARAMS, "png"))
        archive.writestr("__MACOSX/clip/._frame_0.png", b"\x00\x05\x16\x07")
        for t in range(6):
            archive.writestr(f"clip/notes_{t}.txt", b"not a frame")
    result = decode_video(buffer.getvalue(), "zip")
    assert result.frames == 2
    (warning,) = result.warnings
    assert warning.startswith(
        "left out of the video 7 files of the zip that are not .png frames: "
        "'clip/frame_1.jpg', 'clip/notes_0.txt', 'clip/notes_1.txt', 'clip/notes_2.txt', "
        "'clip/notes_3.txt' and 2 more; if any is a frame, send it as a PNG"
    )
    assert decode_video(zip_of({"a.png": (video[0], PARAMS)}), "zip").warnings == ()


def test_overrides_win_over_stored_parameters() -> None:
    result = decode_video(tiff_bytes(codes()), "tif", {"alpha": 4.0, "bits": None})
    assert result.params.alpha == 4.0 and result.params.bits == 8


def test_read_video_from_a_path(tmp_path) -> None:
    path = tmp_path / "clip.npy"
    path.write_bytes(npy_bytes(codes()))
    assert read_video(path, FLAGS).frames == 4


def test_a_video_file_without_a_suffix_is_read_by_its_content(tmp_path) -> None:
    """``mcam video clip`` (no suffix) or ``<(cat clip.npy)`` (``/dev/fd/63``) was
    "unsupported wrapped-video format" though its bytes show the format; a file whose
    bytes show none is still refused by name."""
    (tmp_path / "clip").write_bytes(npy_bytes(codes()))
    assert read_video(tmp_path / "clip", FLAGS).frames == 4
    (tmp_path / "notes").write_bytes(b"no video here")
    with pytest.raises(UnsupportedFormatError, match="unsupported wrapped-video format"):
        read_video(tmp_path / "notes", FLAGS)


def test_a_second_array_in_the_npy_file_is_refused_not_dropped() -> None:
    data = npy_bytes(codes()) + npy_bytes(codes())
    with pytest.raises(InvalidInputError, match="bytes after its array of shape .4, 6, 5.; send"):
        decode_video(data, "npy", FLAGS)


@pytest.mark.parametrize("channels", [3, 1])
def test_one_frame_with_channels_is_not_read_as_a_video_of_thin_frames(channels: int) -> None:
    """A single colour frame (H x W x 3) sent as a video was read as H frames W x 3
    pixels wide: its job made EXRs of strips, or was refused for HDR10 frames under
    64 x 64 pixels with 'ask for outputs=sdr,exr_zip'."""
    frame = codes(1, channels)[0]
    with pytest.raises(InvalidInputError, match=r"shape \(6, 5, \d\) reads as one frame") as error:
        decode_video(npy_bytes(frame), "npy", FLAGS)
    assert f"1 x 6 x 5 x {channels}" in str(error.value)


def test_a_video_of_frames_three_pixels_wide_is_read_with_its_channel_axis() -> None:
    """The way the refusal above gives for frames that really are 3 pixels wide."""
    frames = codes(1, 3)[0]
    with pytest.raises(InvalidInputError, match=r"T x H x 3 x 1 \(array\[\.\.\., None\]\)"):
        decode_video(npy_bytes(frames), "npy", FLAGS)
    thin = decode_video(npy_bytes(frames[..., None]), "npy", FLAGS)
    assert thin.frames == 6 and thin.codes.shape[1:] == (5, 3, 1)


def test_a_video_of_frames_one_pixel_wide_is_told_its_shape() -> None:
    """A line sensor's clip (clip frames may be 1 pixel wide), T x H x 1, is refused as
    one frame H x W x 1; the refusal gave no shape for such a video, only for frames 3
    pixels wide."""
    frames = codes(1, 1)[0]
    clip = FLAGS | {"encoding": "clip"}
    with pytest.raises(InvalidInputError, match=r"frames 1 pixel wide is T x H x 1 x 1 \(array"):
        decode_video(npy_bytes(frames), "npy", clip)
    thin = decode_video(npy_bytes(frames[..., None]), "npy", clip)
    assert thin.frames == 6 and thin.codes.shape[1:] == (5, 1, 1)


@pytest.mark.parametrize("shape", [(6, 5), (2, 3, 6, 5, 1), (6,), ()])
def test_arrays_of_no_video_shape_say_how_to_shape_one(shape: tuple[int, ...]) -> None:
    """Every shape but T x H x W[x C] was told 'send a single frame as a frame, not a
    video', a 5-D or 1-D array too; a 2-D one was not told how to send one frame."""
    with pytest.raises(InvalidInputError) as caught:
        decode_video(npy_bytes(np.zeros(shape, np.uint8)), "npy", FLAGS)
    if len(shape) == 2:
        assert "reads as one frame (H x W): send a frame" in caught.value.message
        assert "1 x 6 x 5 (array[None])" in caught.value.message
    else:
        assert "single frame" not in caught.value.message
        assert "save the frames stacked as one array T x H x W" in caught.value.message


def test_limits_are_checked() -> None:
    with pytest.raises(ImageTooLargeError, match="frames"):
        decode_video(npy_bytes(codes(5)), "npy", FLAGS, VideoLimits(frames=4))
    with pytest.raises(ImageTooLargeError, match="pixels"):
        decode_video(tiff_bytes(codes()), "tiff", limits=VideoLimits(pixels=29))
    with pytest.raises(ImageTooLargeError, match="frames"):
        decode_video(zip_bytes(codes(5)), "zip", limits=VideoLimits(frames=4))
    with pytest.raises(ImageTooLargeError, match="more than 4 pages"):
        decode_video(tiff_bytes(codes(5)), "tiff", limits=VideoLimits(frames=4))


@pytest.mark.parametrize("fmt", ["npy", "tiff", "zip"])
def test_the_whole_video_is_bounded_in_code_values(fmt: str) -> None:
    """4 frames of 6 x 5 codes: 120 values pass a limit of 120 and fail one of 119."""
    data = {"npy": npy_bytes, "tiff": tiff_bytes, "zip": zip_bytes}[fmt](codes())
    assert decode_video(data, fmt, FLAGS, VideoLimits(samples=120)).frames == 4
    with pytest.raises(ImageTooLargeError, match=r"120 code values \(4 x 6 x 5\).*119"):
        decode_video(data, fmt, FLAGS, VideoLimits(samples=119))


def test_a_zip_entry_that_inflates_past_any_frame_is_not_inflated() -> None:
    """A zip bomb: 4 MiB of zeros in a few KB, declared as a PNG frame."""
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w", compression=zipfile.ZIP_DEFLATED) as archive:
        archive.writestr("frame_0.png", bytes(4 * 2**20))
    assert len(buffer.getvalue()) < 2**15
    with pytest.raises(ImageTooLargeError, match="frame_0.png inflates to 4194304 bytes"):
        decode_video(buffer.getvalue(), "zip", FLAGS, VideoLimits(pixels=64 * 64))


def with_entry_fields(data: bytes, flags: int | None = None, method: int | None = None) -> bytes:
    """``data``, a zip, with every entry's general-purpose flags and/or compression method
    set in its local header and its central directory record (the data left as it is)."""
    patched = bytearray(data)
    for signature, flags_at in ((b"PK\x03\x04", 6), (b"PK\x01\x02", 8)):
        at = patched.find(signature)
        while at >= 0:
            if flags is not None:
                struct.pack_into("<H", patched, at + flags_at, flags)
            if method is not None:
                struct.pack_into("<H", patched, at + flags_at + 2, method)
            at = patched.find(signature, at + 4)
    return bytes(patched)


@pytest.mark.parametrize(
    ("fields", "expected"),
    [({"flags": 1}, "encrypted"), ({"method": 9}, "compressed with method 9")],
    ids=["encrypted", "deflate64"],
)
def test_a_zip_it_cannot_inflate_says_why_not_truncated(
    fields: dict[str, int], expected: str
) -> None:
    """A password-protected zip, or one compressed with a method zipfile lacks (Deflate64,
    method 9), is whole: it was called "truncated or corrupt" with "send the complete,
    unmodified file", which the client had done."""
    data = with_entry_fields(zip_bytes(codes(2)), **fields)
    with pytest.raises(UnsupportedFormatError, match=expected) as err:
        decode_video(data, "zip")
    assert "truncated" not in err.value.message
    assert "Deflate" in err.value.message and "frame_0.png" in err.value.message


def lying_zip(png: bytes, hidden_mib: int, method: int = zipfile.ZIP_DEFLATED) -> bytes:
    """A zip whose one entry declares ``len(png)`` bytes (with the PNG's CRC) while its
    stream, deflate or (``method``) bzip2, goes on inflating ``hidden_mib`` MiB of zeros
    past them."""
    packer: Any = (bz2.BZ2Compressor(9) if method == zipfile.ZIP_BZIP2
                   else zlib.compressobj(9, zlib.DEFLATED, -15))  # fmt: skip
    stream = packer.compress(png)
    for _ in range(hidden_mib):
        stream += packer.compress(bytes(2**20))
    stream += packer.flush()
    name, crc = b"frame_0.png", zlib.crc32(png)
    sizes = (crc, len(stream), len(png), len(name))
    local = struct.pack("<4s5H3L2H", b"PK\x03\x04", 20, 0, method, 0, 0, *sizes, 0) + name
    central = struct.pack("<4s6H3L5H2L", b"PK\x01\x02", 20, 20, 0, method, 0, 0, *sizes,
                          0, 0, 0, 0, 0, 0) + name  # fmt: skip
    end = struct.pack("<4s4H2LH", b"PK\x05\x06", 0, 0, 1, 1, len(central),
                      len(local) + len(stream), 0)  # fmt: skip
    return local + stream + central + end


def test_a_zip_entry_lying_about_its_size_is_inflated_only_that_far() -> None:
    """zipfile's one-call read inflated up to 2 GiB before cutting to the declared size
    (a 1 MB upload took the API to 2.2 GiB); chunked reads stop at the declared size."""
    png = encode_frame(codes(1)[0], PARAMS, "png")
    data = lying_zip(png, hidden_mib=256)
    tracemalloc.start()
    try:
        video = decode_video(data, "zip", None, VideoLimits(pixels=64 * 64))
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert video.codes.shape == (1, *codes(1)[0].shape)
    assert peak < 32 * 2**20, f"{peak / 2**20:.0f} MiB held while decoding a {len(data)} B zip"


def test_a_bzip2_zip_entry_is_refused_before_it_is_inflated() -> None:
    """zipfile inflates a bzip2 (or LZMA) entry's whole read of compressed bytes at once,
    past its declared size: 796 bytes of bzip2 declaring a 200-byte PNG took the API to
    1.1 GB (512 MiB of zeros hidden). Only stored and Deflate entries are inflated."""
    png = encode_frame(codes(1)[0], PARAMS, "png")
    data = lying_zip(png, hidden_mib=16, method=zipfile.ZIP_BZIP2)
    tracemalloc.start()
    try:
        with pytest.raises(UnsupportedFormatError, match="compressed with method 12"):
            decode_video(data, "zip", None, VideoLimits(pixels=64 * 64))
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert peak < 4 * 2**20, f"{peak / 2**20:.0f} MiB held while refusing a {len(data)} B zip"


@pytest.mark.parametrize(
    ("data", "fmt", "error"),
    [
        (npy_bytes(codes()[0]), "npy", InvalidInputError),
        (npy_bytes(codes().astype(np.float32)), "npy", InvalidInputError),
        (npy_bytes(codes().astype(np.uint16) * 300), "npy", InvalidInputError),
        (tiff_bytes(codes())[:200], "tiff", InvalidInputError),
        (b"not a zip", "zip", InvalidInputError),
        (zip_bytes(codes(0), []), "zip", InvalidInputError),
        (npy_bytes(codes()), "mp4", UnsupportedFormatError),
    ],
    ids=["one-frame", "float", "too-many-bits", "truncated", "not-zip", "no-png", "suffix"],
)
def test_bad_videos_are_refused(data: bytes, fmt: str, error: type[Exception]) -> None:
    with pytest.raises(error):
        decode_video(data, fmt, FLAGS)


@pytest.mark.parametrize(
    ("data", "fmt", "fragment"),
    [
        (npy_bytes(codes(channels=2)), "npy", "1 or 3 channels"),
        (npy_bytes(codes()[:, :1]), "npy", "1 x 5 frame has no neighbours"),
        (tiff_bytes(codes()[:, :, :1]), "tiff", "6 x 1 frame has no neighbours"),
        (zip_bytes(codes()[:, :1, :1]), "zip", "1 x 1 frame has no neighbours"),
    ],
    ids=["two-channels", "one-row", "one-column", "one-pixel"],
)
def test_frames_no_decoder_takes_are_refused_before_any_job(
    data: bytes, fmt: str, fragment: str
) -> None:
    with pytest.raises(InvalidInputError, match=fragment):
        decode_video(data, fmt, FLAGS)


@pytest.mark.parametrize("shape", [(3, 1, 5), (3, 6, 1, 1), (3, 1, 1, 1), (3, 1, 5, 3)])
def test_clip_frames_one_pixel_high_or_wide_are_a_video(shape: tuple[int, ...]) -> None:
    """A clipped sensor never wraps, so its frames need no neighbours (as a still clip
    frame of any size with a pixel decodes)."""
    codes = np.arange(np.prod(shape), dtype=np.uint8).reshape(shape)
    video = decode_video(npy_bytes(codes), "npy", {**FLAGS, "encoding": "clip"})
    np.testing.assert_array_equal(video.codes, codes)


def zip_of(frames: dict[str, tuple[np.ndarray, SensorParams | None]]) -> bytes:
    """A zip of PNG frames, each with its own parameters (None: it stores none)."""
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w") as archive:
        for name, (frame, params) in frames.items():
            archive.writestr(name, encode_frame(frame, params, "png"))
    return buffer.getvalue()


@pytest.mark.parametrize(
    ("second", "named"),
    [
        ((codes()[0][:4], PARAMS), r"in size \(4 x 5 against 6 x 5\)"),
        ((codes()[0], PARAMS.model_copy(update={"alpha": 3.0})), "in alpha;"),
        ((codes()[0], PARAMS.model_copy(update={"gain": 2.0, "read_noise": 0.01})),
         "in gain, read_noise;"),
    ],
    ids=["size", "alpha", "exposure and noise"],
)  # fmt: skip
def test_zip_frames_must_match_and_the_error_names_what_differs(
    second: tuple[np.ndarray, SensorParams], named: str
) -> None:
    data = zip_of({"a.png": (codes()[0], PARAMS), "b.png": second})
    with pytest.raises(InvalidInputError, match=f"b.png differs from a.png {named}"):
        decode_video(data, "zip")


def test_zip_frames_must_share_their_sample_type() -> None:
    """An 8-bit PNG among 16-bit ones (no stored parameters, bits 12 given) was taken as
    12-bit codes 0..255, a frame decoded almost black without a word; the TIFF reader
    refused such pages. The zip is refused, naming the frame."""
    wide = encode_frame(codes()[0].astype(np.uint16) * 16, None, "png")
    narrow = encode_frame(codes()[1], None, "png")
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w") as archive:
        archive.writestr("a.png", wide)
        archive.writestr("b.png", narrow)
    with pytest.raises(
        InvalidInputError, match=r"b.png differs from a.png in sample type \(uint8 against uint16\)"
    ):
        decode_video(buffer.getvalue(), "zip", {**FLAGS, "bits": 12})


def test_zip_frames_may_differ_in_noise_seed() -> None:
    """Frames simulated one by one (``mcam simulate --seed k``) each carry their seed."""
    frames = {f"f{k}.png": (codes()[k], PARAMS.model_copy(update={"seed": k})) for k in range(3)}
    result = decode_video(zip_of(frames), "zip")
    np.testing.assert_array_equal(result.codes, codes()[:3])


def test_later_zip_frames_storing_no_parameters_have_the_first_frames() -> None:
    """Parameters come from the first frame's text chunk, as a TIFF video's from its
    first page: frames after it that stored none (saved again by a tool that drops text
    chunks) were refused, "f1.png: the frame does not store its encoding, bits"."""
    frames = {"f0.png": (codes()[0], PARAMS), "f1.png": (codes()[1], None)}
    result = decode_video(zip_of({**frames, "f2.png": (codes()[2], None)}), "zip")
    np.testing.assert_array_equal(result.codes, codes()[:3])
    assert result.params == PARAMS


def test_a_later_zip_entry_may_inflate_only_to_what_the_first_frame_needs() -> None:
    """A valid PNG followed by 2 MiB of zeros (readers ignore bytes after the image)
    fits the limit for any frame of the pixel bound, but not twice an uncompressed
    PNG of the first frame's 6 x 5 codes and 1 MiB: refused before it is inflated."""
    png = encode_frame(codes()[0], PARAMS, "png")
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w", zipfile.ZIP_DEFLATED) as archive:
        archive.writestr("frame_0.png", png + bytes(2 << 20))
        archive.writestr("frame_1.png", png + bytes(2 << 20))
    with pytest.raises(ImageTooLargeError, match=r"^frame_1.png inflates to \d+ bytes"):
        decode_video(buffer.getvalue(), "zip", limits=VideoLimits(pixels=1024 * 1024))


def test_format_names() -> None:
    assert [video_format(n) for n in ("a.TIF", "b.tiff", "c.npy", "zip")] == [
        "tiff", "tiff", "npy", "zip"
    ]


@pytest.mark.parametrize("content", ["tiff", "npy", "zip"])
@pytest.mark.parametrize("name", ["video.tiff", "video.npy", "video.zip"])
def test_a_video_is_decoded_by_its_content_whatever_its_name(
    tmp_path: Path, content: str, name: str
) -> None:
    """A zip named .tiff was called a corrupt TIFF: the leading bytes decide."""
    video = codes()
    data = {"tiff": tiff_bytes, "npy": npy_bytes, "zip": zip_bytes}[content](video)
    (tmp_path / name).write_bytes(data)
    np.testing.assert_array_equal(read_video(tmp_path / name, FLAGS).codes, video)


def test_zip_without_pngs_says_what_it_holds() -> None:
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w") as archive:
        archive.writestr("notes.txt", "frames to follow")
    with pytest.raises(InvalidInputError, match=r"no \.png frame \(its files: 'notes\.txt'\)"):
        decode_video(buffer.getvalue(), "zip", FLAGS)


@pytest.mark.parametrize("name", ["clip.zip", "clip.npy"])
def test_an_empty_zip_is_called_a_zip_of_no_frame(name: str) -> None:
    """A zip of no entry (``zipfile.ZipFile(path, "w")`` when the glob of the frames
    matched none) is its end record alone: it was "not a zip of PNG frames (bad or
    missing signature) ... not converted to another format, renamed or cut short"."""
    buffer = io.BytesIO()
    zipfile.ZipFile(buffer, "w").close()
    with pytest.raises(InvalidInputError, match=r"^the zip holds no \.png frame \(no file\)"):
        decode_video(buffer.getvalue(), name, FLAGS)


def test_an_npz_is_told_to_be_sent_as_an_npy() -> None:
    """np.savez writes a zip of .npy arrays: it was 'the zip holds no .png frame (1 other
    entries); a wrapped video as a zip is one PNG of codes per frame', not saying what
    the file was or that the same frames go as one .npy."""
    buffer = io.BytesIO()
    np.savez(buffer, codes())
    with pytest.raises(InvalidInputError, match=r"files: 'arr_0\.npy'\); it is a NumPy \.npz"):
        decode_video(buffer.getvalue(), "zip", FLAGS)


def test_a_pytorch_file_is_told_to_be_sent_as_an_npy() -> None:
    """torch.save writes a zip (of data.pkl and the tensors' storages): saved as
    clip.npy, it was "the zip holds no .png frame (its files: 'archive/data.pkl', ...);
    a wrapped video as a zip is one PNG of codes per frame", not saying what it was nor
    how to send its frames."""
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w") as archive:  # the entries torch.save writes
        for name in ("data.pkl", ".format_version", "byteorder", "data/0", "version"):
            archive.writestr(f"archive/{name}", b"\x80\x02")
    with pytest.raises(InvalidInputError, match=r"it is a PyTorch file \(torch.save\)") as error:
        decode_video(buffer.getvalue(), "clip.npy", FLAGS)
    assert "np.save(path, tensor.numpy())" in str(error.value)


@pytest.mark.parametrize(
    ("data", "what"),
    [
        (encode_frame(codes()[0], PARAMS, "png"), "a PNG image, one wrapped frame, not a video"),
        (b"\x76\x2f\x31\x01" + bytes(60), "an OpenEXR image (scene irradiance)"),
        (b"#?RADIANCE\n" + bytes(60), "a Radiance HDR image (scene irradiance)"),
    ],
    ids=["png-frame", "exr", "radiance"],
)
def test_a_frame_or_hdr_image_sent_as_a_video_is_named(data: bytes, what: str) -> None:
    """A PNG frame or an HDR image named as a video was 'not a zip of PNG frames (bad or
    missing signature), nor any video format read here: send the wrapped video's file
    itself, as written (...; not converted to another format, renamed or cut short)'."""
    with pytest.raises(UnsupportedFormatError, match=rf"^the file is {re.escape(what)}"):
        decode_video(data, "zip", FLAGS)


@pytest.mark.parametrize(
    ("fmt", "noun"),
    [("tiff", "a TIFF video"), ("npy", "an npy file"), ("zip", "a zip of PNG frames")],
)
def test_data_of_no_video_format_says_what_to_send(fmt: str, noun: str) -> None:
    """A JPEG named as a video was called a truncated or corrupt file of that format."""
    with pytest.raises(InvalidInputError) as refused:
        decode_video(b"\xff\xd8\xff\xe0 a JPEG" * 5, fmt, FLAGS)
    message = refused.value.message
    assert f"the data is not {noun}" in message and "send the wrapped video's file" in message
    assert "truncated" not in message


def test_a_truncated_tiff_video_is_refused_not_cut_short() -> None:
    video = np.zeros((12, 16, 16), np.uint8)  # pages' data first: the cut loses IFDs
    data = tiff_bytes(video)
    with pytest.raises(InvalidInputError, match="TIFF video is truncated or corrupt"):
        decode_video(data[: len(data) // 2], "tiff")


def test_a_zstandard_tiff_video_is_refused_as_unsupported_not_corrupt() -> None:
    """Its pages were 'truncated or corrupt (No module named 'compression')' on Python
    3.11."""
    data = bytearray(tiff_bytes(codes(frames=3)))
    with tifffile.TiffFile(io.BytesIO(data)) as tif:
        entries = [page.tags["Compression"].offset for page in tif.pages]
    assert len(entries) == 3
    for entry in entries:
        struct.pack_into("<HHIH", data, entry, 259, 3, 1, 50000)
    with pytest.raises(UnsupportedFormatError, match=r"ZSTD \(50000\).*deflate"):
        decode_video(bytes(data), "tiff")


def test_a_miniswhite_tiff_videos_codes_are_what_its_pages_stand_for() -> None:
    """A MinIsWhite video's pages were read as stored: every frame's codes came out as
    255 - code."""
    video = codes(frames=3)
    data = miniswhite_tiff(255 - video, PARAMS)
    np.testing.assert_array_equal(decode_video(data, "tiff").codes, video)


def test_a_separate_plane_tiff_video_is_read_samples_last() -> None:
    video = codes(frames=3, channels=3)
    buffer = io.BytesIO()
    tifffile.imwrite(
        buffer, np.moveaxis(video, -1, 1), photometric="rgb", planarconfig="separate",
        description=PARAMS.model_dump_json(), metadata=None,
    )  # fmt: skip
    np.testing.assert_array_equal(decode_video(buffer.getvalue(), "tiff").codes, video)


@pytest.mark.parametrize("frames", [3, 4])
def test_three_or_four_frames_tifffile_stored_as_colour_planes_are_not_one_frame(
    frames: int,
) -> None:
    """tifffile.imwrite(path, frames) stores a stack of 3 (or 4) grey frames as one page
    of RGB (RGBA) planes: 3 frames became one colour frame without a word, and 4 were
    told 'give H x W x 3 (RGB without its alpha channel)'."""
    stack = codes(frames)
    buffer = io.BytesIO()
    alpha = {"extrasamples": ["unassalpha"]} if frames == 4 else {}
    tifffile.imwrite(buffer, stack, photometric="rgb", planarconfig="separate", **alpha)
    with pytest.raises(InvalidInputError, match=rf"one page of {frames} planes") as caught:
        decode_video(buffer.getvalue(), "tiff", FLAGS)
    assert "photometric='minisblack'" in caught.value.message
    pages = io.BytesIO()
    tifffile.imwrite(pages, stack, photometric="minisblack")
    np.testing.assert_array_equal(decode_video(pages.getvalue(), "tiff", FLAGS).codes, stack)


@pytest.mark.parametrize(
    ("shape", "axes", "named"),
    [
        ((4, 3, 6, 5), "TCYX", "4 frames x 3 channels"),
        ((4, 2, 6, 5), "TZYX", "4 frames x 2 slices"),
    ],
)
def test_an_imagej_hyperstack_is_not_read_as_one_frame_a_page(
    shape: tuple[int, ...], axes: str, named: str
) -> None:
    """ImageJ stores a hyperstack's channels (or slices) as pages of their own: 4 colour
    frames of 3 channels became a grey video of 12 frames without a word."""
    buffer = io.BytesIO()
    stack = np.random.default_rng(0).integers(0, 256, shape).astype(np.uint8)
    tifffile.imwrite(buffer, stack, imagej=True, metadata={"axes": axes})
    with pytest.raises(InvalidInputError, match=rf"ImageJ hyperstack of {named}: its (12|8) pages"):
        decode_video(buffer.getvalue(), "tiff", FLAGS)
    plain = io.BytesIO()
    tifffile.imwrite(plain, stack[:, 0], imagej=True, metadata={"axes": "TYX"})
    np.testing.assert_array_equal(decode_video(plain.getvalue(), "tiff", FLAGS).codes, stack[:, 0])


def tiff_pages(*pages: tuple[np.ndarray, SensorParams | None]) -> bytes:
    """A TIFF video written a page at a time, each page with its own description."""
    buffer = io.BytesIO()
    with tifffile.TiffWriter(buffer) as writer:
        for frame, params in pages:
            description = params.model_dump_json() if params else None
            writer.write(frame, description=description, metadata=None)
    return buffer.getvalue()


@pytest.mark.parametrize("kinds", [(1,), (4,), (4, 5), (5, 4), (1, 4)])
def test_a_tiff_videos_thumbnails_and_masks_are_not_frames(kinds: tuple[int, ...]) -> None:
    """A page per frame and, after each, a thumbnail (NewSubfileType 1) or a 1-bit
    transparency mask (4; 5: a reduced-resolution mask, half its size) per entry of
    ``kinds`` was refused: they were read as frames whose size or sample type (bool)
    differs from the first page's."""
    video = codes(3)
    buffer = io.BytesIO()
    with tifffile.TiffWriter(buffer) as writer:
        for index, frame in enumerate(video):
            description = PARAMS.model_dump_json() if index == 0 else None
            writer.write(frame, description=description, metadata=None)
            for kind in kinds:
                if kind & 4:
                    write_mask(writer, frame.shape, kind)
                else:
                    writer.write(frame[::2, ::2], subfiletype=kind, metadata=None)
    result = decode_video(buffer.getvalue(), "tiff")
    np.testing.assert_array_equal(result.codes, video)
    assert result.frames == 3


TWELVE_BIT = SensorParams(encoding="modulo", bits=12)


@pytest.mark.parametrize(
    ("second", "named"),
    [
        ((codes()[1].astype(np.uint16) * 16, TWELVE_BIT),
         r"in sample type \(uint16 against uint8\), encoding, bits;"),
        ((codes()[1].astype(np.uint16), None), r"in sample type \(uint16 against uint8\);"),
        ((codes()[1], PARAMS.model_copy(update={"gain": 2.0})), "in gain;"),
        ((codes()[1][:4], None), r"in size \(4 x 5 against 6 x 5\);"),
    ],
    ids=["12-bit modulo", "16-bit samples", "gain", "size"],
)  # fmt: skip
def test_tiff_pages_must_match_and_the_error_names_what_differs(
    second: tuple[np.ndarray, SensorParams | None], named: str
) -> None:
    """Every page was decoded with page 0's parameters (a 12-bit page as 8-bit codes)."""
    data = tiff_pages((codes()[0], PARAMS), second)
    with pytest.raises(InvalidInputError, match=f"^page 1 differs from page 0 {named}"):
        decode_video(data, "tiff")


@pytest.mark.parametrize("bits", [0, 12])
def test_a_later_page_of_a_sample_size_not_read_is_refused_naming_it(bits: int) -> None:
    """Page 1 of 0 or 12 bits a sample was said to differ from page 0 "in sample type
    (None against uint8)" (or uint16), where a frame of them is refused by its size."""
    data = with_short(tiff_bytes(codes()), "BitsPerSample", bits, page=1)
    with pytest.raises(UnsupportedFormatError, match=rf"samples of {bits} bits.*8- or 16"):
        decode_video(data, "tiff")


def test_tiff_pages_may_differ_in_noise_seed_and_need_not_repeat_parameters() -> None:
    seeded = PARAMS.model_copy(update={"seed": 7})
    data = tiff_pages((codes()[0], PARAMS), (codes()[1], None), (codes()[2], seeded))
    result = decode_video(data, "tiff")
    np.testing.assert_array_equal(result.codes, codes()[:3])
    assert result.params == PARAMS


def test_a_bad_png_in_a_zip_names_its_entry() -> None:
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w") as archive:
        archive.writestr("frame_0.png", encode_frame(codes(1)[0], PARAMS, "png"))
        archive.writestr("frame_1.png", b"not a png")
    with pytest.raises(InvalidInputError, match=r"^frame_1.png: the data is not a PNG image"):
        decode_video(buffer.getvalue(), "zip")


@pytest.mark.parametrize(
    ("entry", "said"), [(b"", "the entry is empty"), (b"GIF89a", "the data is not a PNG image")]
)
def test_an_entry_of_no_frame_is_told_what_a_zip_entry_holds(entry: bytes, said: str) -> None:
    """An empty entry was "not a PNG image (bad or missing signature)", and either was
    told to send a .tiff or .npy frame, or raw codes with format=raw, none of which a
    zip of frames takes."""
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w") as archive:
        archive.writestr("frame_0.png", encode_frame(codes(1)[0], PARAMS, "png"))
        archive.writestr("frame_1.png", entry)
    with pytest.raises(InvalidInputError, match=f"^frame_1.png: {said}") as error:
        decode_video(buffer.getvalue(), "zip")
    assert "format=raw" not in str(error.value)
    assert ".npy" not in str(error.value)


def test_an_hdr_image_in_a_zip_is_still_named_as_such() -> None:
    """The frame reader says what an HDR image is and where it goes; the zip's own check
    of its entries leaves such an entry to it."""
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w") as archive:
        archive.writestr("frame_0.png", encode_exr(np.ones((8, 8))))
    with pytest.raises(UnsupportedFormatError, match="^frame_0.png: the file is an OpenEXR"):
        decode_video(buffer.getvalue(), "zip")


def test_a_zip_of_too_many_entries_is_refused_from_its_directory_record() -> None:
    """zipfile builds an object per entry before any count can be checked."""
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w") as archive:
        for n in range(100):
            archive.writestr(f"note_{n}.txt", b"")
    data = buffer.getvalue()
    assert central_entries(data, 200) == 100 and central_entries(data, 20) == 21
    with pytest.raises(ImageTooLargeError, match="more than 84 entries; .* at most 10 frames"):
        decode_video(data, "zip", FLAGS, VideoLimits(frames=10))
    assert central_entries(b"not a zip", 10) is None


def test_a_macos_zip_of_as_many_frames_as_the_limit_is_read() -> None:
    """A zip made on macOS holds a resource fork per frame and folder entries besides:
    10 frames made 23 entries, refused as 'more than 20 entries' at a limit of 10 frames."""
    video = codes(10)
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w") as archive:
        for folder in ("clip/", "__MACOSX/", "__MACOSX/clip/"):
            archive.writestr(folder, b"")
        for t, frame in enumerate(video):
            archive.writestr(f"clip/frame_{t}.png", encode_frame(frame, PARAMS, "png"))
            archive.writestr(f"__MACOSX/clip/._frame_{t}.png", b"\x00\x05\x16\x07")
    result = decode_video(buffer.getvalue(), "zip", FLAGS, VideoLimits(frames=10))
    np.testing.assert_array_equal(result.codes, video)


def test_a_dark_frame_of_a_zip_is_no_eight_bit_warning() -> None:
    """A 16-bit clip whose first frame is dark (every code below 256) is not an 8-bit
    clip: the check is of the whole clip's codes, as for a TIFF or an npy."""
    params = PARAMS.model_copy(update={"bits": 16})
    dark, bright = np.full((6, 5), 100, np.uint16), np.full((6, 5), 40000, np.uint16)
    video = decode_video(zip_of({"a.png": (dark, params), "b.png": (bright, params)}), "zip")
    assert video.warnings == ()
    video = decode_video(zip_of({"a.png": (dark, params), "b.png": (dark, params)}), "zip")
    assert video.warnings == (
        "every code is below 256 although bits is 16: if the frame is 8-bit, give bits 8 "
        "(--bits 8, or the form field bits=8)",
    )
