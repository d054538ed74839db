"""Tests of models/frames.py: wrapped-frame files and raw uploads."""

from __future__ import annotations

import io
import os
import re
import struct
import tracemalloc
import zlib
from pathlib import Path

import numpy as np
import pytest
import tifffile
from hypothesis import given, settings
from hypothesis import strategies as st
from PIL import Image, PngImagePlugin

from models.errors import (
    FormatCannotHoldError,
    ImageTooLargeError,
    InvalidInputError,
    MissingParameterError,
    UnsupportedFormatError,
)
from models.file_magic import PNG_SIGNATURE
from models.formation import SensorParams
from models.frames import (
    FRAME_FORMATS,
    PNG_KEYWORD,
    WrappedFrame,
    decode_frame,
    decode_raw,
    encode_frame,
    frame_format,
    read_frame,
    write_frame,
)
from models.png_chunks import METADATA_BYTES
from models.stored_params import MAX_PARAMS_TEXT
from models.winding_files import decode_winding

PARAMS_8 = SensorParams(encoding="mantissa", alpha=2.0, bits=8, gain=3.5, seed=7)
PARAMS_12 = SensorParams(encoding="modulo", bits=12, read_noise=0.01, max_wraps=16.0)


def random_codes(shape: tuple[int, ...], bits: int, seed: int = 0) -> np.ndarray:
    dtype = np.uint8 if bits <= 8 else np.uint16
    return np.random.default_rng(seed).integers(0, 1 << bits, shape).astype(dtype)


def png_chunk(kind: bytes, payload: bytes) -> bytes:
    body = kind + payload
    return struct.pack(">I", len(payload)) + body + struct.pack(">I", zlib.crc32(body))


def png_header_only(width: int, height: int) -> bytes:
    """A 16-bit gray PNG whose IHDR claims ``width x height`` but whose IDAT holds 4 bytes."""
    header = png_chunk(b"IHDR", struct.pack(">IIBBBBB", width, height, 16, 0, 0, 0, 0))
    return b"\x89PNG\r\n\x1a\n" + header + png_chunk(b"IDAT", zlib.compress(bytes(64))[:4])


@pytest.mark.parametrize(
    ("name", "expected"),
    [
        ("x.png", "png"),
        ("dir.v2/frame.PNG", "png"),
        (".tif", "tiff"),
        ("tiff", "tiff"),
        ("a.tiff", "tiff"),
        ("npy", "npy"),
        (Path("f.npy"), "npy"),
    ],
)
def test_frame_format_maps_names(name: str | Path, expected: str) -> None:
    assert frame_format(name) == expected
    assert expected in FRAME_FORMATS


@pytest.mark.parametrize("name", ["x.jpg", "exr", "frame", ""])
def test_frame_format_rejects_with_the_valid_list(name: str) -> None:
    with pytest.raises(UnsupportedFormatError, match=r"\.png.*\.tiff.*\.npy"):
        frame_format(name)


@pytest.mark.parametrize(
    ("fmt", "shape", "params"),
    [
        ("png", (17, 23), PARAMS_8),
        ("png", (17, 23), PARAMS_12),
        ("tiff", (17, 23), PARAMS_12),
        ("tiff", (17, 23, 3), PARAMS_8),
        ("tiff", (9, 5, 5), PARAMS_12),
    ],
)
def test_round_trip_keeps_codes_and_params(
    tmp_path: Path, fmt: str, shape: tuple[int, ...], params: SensorParams
) -> None:
    codes = random_codes(shape, params.bits)
    path = tmp_path / f"frame.{fmt}"
    write_frame(path, codes, params)
    frame = read_frame(path)
    assert isinstance(frame, WrappedFrame)
    assert frame.params == params
    assert frame.codes.shape == shape
    assert frame.codes.dtype == params.code_dtype
    np.testing.assert_array_equal(frame.codes, codes)


@pytest.mark.parametrize("fmt", ["png", "tiff", "npy"])
def test_a_frame_file_without_a_suffix_is_read_by_its_content(tmp_path: Path, fmt: str) -> None:
    """``mcam reconstruct frame`` (no suffix) or ``<(cat f.png)`` (``/dev/fd/63``) was
    "unsupported wrapped-frame format 'frame'" though its bytes show the format, which
    decides whatever the name says. A file whose bytes show none is refused by name."""
    codes = random_codes((4, 5), 8)
    (tmp_path / "frame").write_bytes(encode_frame(codes, PARAMS_8, fmt))
    frame = read_frame(tmp_path / "frame", PARAMS_8.model_dump())
    np.testing.assert_array_equal(frame.codes, codes)
    read, write = os.pipe()
    try:
        os.write(write, encode_frame(codes, PARAMS_8, fmt))
        os.close(write)
        frame = read_frame(f"/dev/fd/{read}", PARAMS_8.model_dump())
    finally:
        os.close(read)
    np.testing.assert_array_equal(frame.codes, codes)
    (tmp_path / "notes").write_bytes(b"no frame here")
    with pytest.raises(UnsupportedFormatError, match="unsupported wrapped-frame format"):
        read_frame(tmp_path / "notes")


def test_png_bit_depth_follows_bits() -> None:
    eight = Image.open(io.BytesIO(encode_frame(random_codes((4, 4), 8), PARAMS_8, "png")))
    sixteen = Image.open(io.BytesIO(encode_frame(random_codes((4, 4), 12), PARAMS_12, "png")))
    assert eight.mode == "L"
    assert sixteen.mode.startswith("I;16")
    assert SensorParams.model_validate_json(sixteen.text[PNG_KEYWORD]) == PARAMS_12


def test_npy_stores_codes_only_and_needs_params() -> None:
    codes = random_codes((6, 7), 12)
    data = encode_frame(codes, PARAMS_12, "npy")
    np.testing.assert_array_equal(np.load(io.BytesIO(data)), codes)
    with pytest.raises(MissingParameterError):
        decode_frame(data, "npy")
    frame = decode_frame(data, "npy", {"encoding": "modulo", "bits": 12})
    np.testing.assert_array_equal(frame.codes, codes)


@settings(max_examples=25, deadline=None)
@given(
    bits=st.integers(1, 16),
    fmt=st.sampled_from(FRAME_FORMATS),
    height=st.integers(1, 9),
    width=st.integers(1, 9),
    seed=st.integers(0, 2**16),
)
def test_round_trip_any_bit_depth(bits: int, fmt: str, height: int, width: int, seed: int) -> None:
    params = SensorParams(encoding="modulo", bits=bits)
    codes = random_codes((height, width), bits, seed)
    frame = decode_frame(
        encode_frame(codes, params, fmt), fmt, {"encoding": "modulo", "bits": bits}
    )
    np.testing.assert_array_equal(frame.codes, codes)
    assert frame.codes.dtype == params.code_dtype


def test_codes_are_stored_in_the_params_dtype() -> None:
    wide = random_codes((5, 5), 8).astype(np.int32)
    frame = decode_frame(encode_frame(wide, PARAMS_8, "png"), "png")
    assert frame.codes.dtype == np.uint8
    np.testing.assert_array_equal(frame.codes, wide)


def miniswhite_tiff(stored: np.ndarray, params: SensorParams | None = None) -> bytes:
    """``stored`` as the samples of a MinIsWhite TIFF (the largest value black), a page
    per frame of a 3-axis array, storing ``params`` if given."""
    buffer = io.BytesIO()
    description = params.model_dump_json() if params else None
    tifffile.imwrite(
        buffer, stored, photometric="miniswhite", description=description, metadata=None
    )
    return buffer.getvalue()


def test_a_miniswhite_tiff_frames_codes_are_what_it_stands_for() -> None:
    """A MinIsWhite 16-bit TIFF (the largest value black) was read as stored: a 12-bit
    frame's codes came out as 65535 - code and were refused as not 12-bit."""
    codes = random_codes((9, 7), 12)
    data = miniswhite_tiff(65535 - codes, PARAMS_12)
    np.testing.assert_array_equal(decode_frame(data, "tiff").codes, codes)


def test_codes_above_the_bit_depth_are_rejected() -> None:
    data = encode_frame(np.full((3, 3), 300, np.uint16), PARAMS_12, "png")
    with pytest.raises(InvalidInputError, match="2\\^8"):
        decode_frame(data, "png", {"bits": 8})
    with pytest.raises(InvalidInputError, match="2\\^8"):
        encode_frame(np.full((3, 3), 300, np.uint16), PARAMS_8, "npy")


@pytest.mark.parametrize(
    "array",
    [np.zeros((4, 4), np.float32), np.zeros(16, np.uint8), np.zeros((2, 2, 2, 2), np.uint8)],
)
def test_npy_with_wrong_dtype_or_shape_is_rejected(array: np.ndarray) -> None:
    buffer = io.BytesIO()
    np.save(buffer, array)
    with pytest.raises(InvalidInputError, match="integers|H x W"):
        decode_frame(buffer.getvalue(), "npy", {"encoding": "modulo", "bits": 8})


@pytest.mark.parametrize(
    ("mode", "said"), [("P", "its samples are indices"), ("LA", "grey with an alpha channel")]
)
def test_a_grey_png_of_a_palette_or_alpha_is_not_told_to_store_colour(
    mode: str, said: str
) -> None:
    """A palette PNG of grey codes (a PNG optimiser's) or a grey one with alpha was told
    "store colour frames as TIFF", though it holds no colour."""
    buffer = io.BytesIO()
    Image.fromarray(random_codes((4, 4), 8)).convert(mode).save(buffer, format="PNG")
    with pytest.raises(UnsupportedFormatError, match=f"mode {mode}; {said}") as caught:
        decode_frame(buffer.getvalue(), "png", {"encoding": "modulo", "bits": 8})
    assert "TIFF" not in caught.value.message


def test_colour_png_is_refused_with_a_pointer_to_tiff() -> None:
    """Writing one is a 422 (the PNG cannot hold the result); reading one, a 415 (the
    upload's format is not read)."""
    with pytest.raises(FormatCannotHoldError, match="tiff") as caught:
        encode_frame(random_codes((4, 4, 3), 8), PARAMS_8, "png")
    assert caught.value.http_status == 422
    buffer = io.BytesIO()
    Image.fromarray(random_codes((4, 4, 3), 8)).save(buffer, format="PNG")
    with pytest.raises(UnsupportedFormatError, match="TIFF"):
        decode_frame(buffer.getvalue(), "png", {"encoding": "modulo", "bits": 8})


def low_depth_png(values: np.ndarray, depth: int) -> bytes:
    """A 1-, 2- or 4-bit grayscale PNG of ``values`` (< 2^depth), as other software
    writes a low-bit-depth sensor's frame or a small W map."""
    image = Image.fromarray(values.astype(bool) if depth == 1 else values.astype(np.uint8))
    buffer = io.BytesIO()
    image.save(buffer, format="PNG", bits=depth)
    data = buffer.getvalue()
    assert data[24] == depth  # the IHDR's bit depth
    return data


@pytest.mark.parametrize("depth", [1, 2, 4])
def test_low_bit_depth_pngs_are_read_as_stored(depth: int) -> None:
    """Pillow widens a 1-, 2- or 4-bit grayscale PNG's samples to 0..255 (a 2-bit 3
    reads 255): such a frame with bits 2 or 4 was refused as 'not 2-bit', with bits 8
    decoded codes 85 or 17 times too large without a word, and a 1-bit one was refused
    as 'mode 1'; a W map written so read W 85 times too large."""
    values = random_codes((5, 7), depth)
    frame = decode_frame(low_depth_png(values, depth), "png", {"encoding": "modulo", "bits": depth})
    np.testing.assert_array_equal(frame.codes, values)
    np.testing.assert_array_equal(decode_winding(low_depth_png(values, depth), "png"), values)


def test_a_1_bit_npy_frame_of_booleans_is_read_as_codes_0_and_1() -> None:
    """It was refused as "codes must be integers (uint8 or uint16), got dtype bool; a
    wrapped frame stores the raw sensor codes, not normalized floats", where a 1-bit PNG
    or TIFF frame is read as codes 0 and 1."""
    values = random_codes((5, 7), 1)
    buffer = io.BytesIO()
    np.save(buffer, values.astype(bool))
    frame = decode_frame(buffer.getvalue(), "npy", {"encoding": "modulo", "bits": 1})
    assert frame.codes.dtype == np.uint8
    np.testing.assert_array_equal(frame.codes, values)


def png_storing(text: str) -> bytes:
    """A 4 x 4 8-bit PNG frame whose parameter chunk holds ``text`` (another writer's)."""
    info = PngImagePlugin.PngInfo()
    info.add_text(PNG_KEYWORD, text)
    buffer = io.BytesIO()
    Image.fromarray(np.zeros((4, 4), np.uint8)).save(buffer, format="PNG", pnginfo=info)
    return buffer.getvalue()


def test_single_channel_png_is_squeezed() -> None:
    codes = random_codes((5, 6, 1), 8)
    frame = decode_frame(encode_frame(codes, PARAMS_8, "png"), "png")
    np.testing.assert_array_equal(frame.codes, codes[:, :, 0])


@pytest.mark.parametrize("fmt", FRAME_FORMATS)
def test_truncated_or_garbage_files_are_invalid_input(fmt: str) -> None:
    data = encode_frame(random_codes((64, 64), 12), PARAMS_12, fmt)
    for broken in (data[: len(data) // 2], data[:10], b"not an image at all" * 10):
        with pytest.raises(InvalidInputError):
            decode_frame(broken, fmt, {"encoding": "modulo", "bits": 12})


def test_a_png_with_a_zero_size_header_is_named_damaged() -> None:
    header = struct.pack(">IIBBBBB", 0, 0, 8, 0, 0, 0, 0)
    chunk = struct.pack(">I", len(header)) + b"IHDR" + header
    data = PNG_SIGNATURE + chunk + struct.pack(">I", zlib.crc32(chunk[4:]))
    with pytest.raises(InvalidInputError, match="PNG's header is damaged"):
        decode_frame(data, "png", {"encoding": "modulo", "bits": 8})
    with pytest.raises(InvalidInputError, match="not a PNG image"):
        decode_frame(b"GIF89a" + data, "png", {"encoding": "modulo", "bits": 8})


@pytest.mark.parametrize("fmt", FRAME_FORMATS)
@pytest.mark.parametrize("data", [b"\xff\xd8\xff\xe0 a JPEG", b"\x89PN"], ids=["jpeg", "cut"])
def test_data_of_no_frame_format_is_refused_saying_what_to_send(fmt: str, data: bytes) -> None:
    """A garbage .png was 'not a PNG image (bad or missing signature)', a garbage .tiff
    or .npy 'truncated or corrupt (not a TIFF file: header=...)', none saying what to
    send instead."""
    with pytest.raises(InvalidInputError, match=r"^the data is not an? (PNG|TIFF|npy)") as caught:
        decode_frame(data, fmt, {"encoding": "modulo", "bits": 8})
    assert "send the frame's file itself, as written (.png, .tiff/.tif or .npy" in str(
        caught.value
    )


def test_bad_params_json_is_invalid_input() -> None:
    buffer = io.BytesIO()
    tifffile.imwrite(
        buffer, random_codes((4, 4), 8), description='{"encoding": "sideways", "bits": 8}'
    )
    with pytest.raises(InvalidInputError, match="encoding"):
        decode_frame(buffer.getvalue(), "tiff")


#: Our parameters padded past the length that is parsed (json.loads of a 60 MB
#: description took 5-7 s and 1.2 GB), and JSON nested past the parser's recursion limit.
OVERLONG = '{"encoding": "modulo",' + " " * MAX_PARAMS_TEXT + '"bits": 8}'
NESTED = "[" * 5000 + "]" * 5000


@pytest.mark.parametrize(
    "description", ['{"shape": [4, 4]}', "[1, 2]", "hello", "{", OVERLONG, NESTED]
)
def test_foreign_tiff_description_is_not_taken_for_params(description: str) -> None:
    """Text other software wrote in the description: the caller's parameters decide."""
    buffer = io.BytesIO()
    codes = random_codes((4, 4), 8)
    tifffile.imwrite(buffer, codes, description=description)
    with pytest.raises(MissingParameterError):
        decode_frame(buffer.getvalue(), "tiff")
    frame = decode_frame(buffer.getvalue(), "tiff", {"encoding": "modulo", "bits": 8})
    np.testing.assert_array_equal(frame.codes, codes)


def test_a_multi_page_tiff_is_refused_with_a_pointer_to_video() -> None:
    """Pages after the first are not dropped silently: a clip is a video job."""
    buffer = io.BytesIO()
    with tifffile.TiffWriter(buffer) as tif:
        for _ in range(3):
            tif.write(random_codes((4, 4), 8))
    with pytest.raises(InvalidInputError, match="holds more than one page.*/v1/videos"):
        decode_frame(buffer.getvalue(), "tiff", {"encoding": "modulo", "bits": 8})


def with_thumbnails(codes: np.ndarray, *first: bool) -> bytes:
    """A TIFF of ``codes`` (parameters in its description) and, as cameras and editors
    write them, a thumbnail of it (NewSubfileType 1) per entry of ``first``: before the
    image where True, after it where False."""
    thumbnail = codes[::4, ::4] // 2
    buffer = io.BytesIO()
    with tifffile.TiffWriter(buffer) as tif:
        for before in first:
            if before:
                tif.write(thumbnail, subfiletype=1, metadata=None)
        tif.write(codes, description=PARAMS_8.model_dump_json(), metadata=None)
        for before in first:
            if not before:
                tif.write(thumbnail, subfiletype=1, metadata=None)
    return buffer.getvalue()


@pytest.mark.parametrize("first", [(False,), (True,), (False, False, False), (True, False)])
def test_a_tiff_frame_with_thumbnails_is_read_as_its_full_resolution_page(
    first: tuple[bool, ...],
) -> None:
    """A reduced-resolution page (NewSubfileType bit 0) is a copy of the image, not a
    frame: a frame with its thumbnail was refused as a multi-page TIFF."""
    codes = random_codes((16, 12), 8)
    frame = decode_frame(with_thumbnails(codes, *first), "tiff")
    np.testing.assert_array_equal(frame.codes, codes)
    assert frame.params == PARAMS_8


def test_a_tiff_of_thumbnails_only_or_two_images_is_refused() -> None:
    buffer = io.BytesIO()
    tifffile.imwrite(buffer, random_codes((4, 4), 8), subfiletype=1, metadata=None)
    with pytest.raises(InvalidInputError, match="only reduced-resolution pages.*plain TIFF"):
        decode_frame(buffer.getvalue(), "tiff", {"encoding": "modulo", "bits": 8})
    buffer = io.BytesIO()
    with tifffile.TiffWriter(buffer) as tif:
        for _ in range(2):
            tif.write(random_codes((8, 8), 8), metadata=None)
            tif.write(random_codes((2, 2), 8), subfiletype=1, metadata=None)
    with pytest.raises(InvalidInputError, match="holds more than one page.*/v1/videos"):
        decode_frame(buffer.getvalue(), "tiff", {"encoding": "modulo", "bits": 8})


def write_mask(tif: tifffile.TiffWriter, shape: tuple[int, ...], kind: int) -> None:
    """Write, as some editors do, a 1-bit transparency-mask page of an image of ``shape``
    (``H x W``, channels aside) to ``tif``: NewSubfileType ``kind``, 4 (a mask the size
    of the image) or 5 (a mask that is also reduced-resolution: half its size)."""
    step = 2 if kind & 1 else 1
    mask = np.ones(shape[:2], np.bool_)[::step, ::step]
    tif.write(mask, subfiletype=kind, photometric="mask", metadata=None)


def with_masks(codes: np.ndarray, before: tuple[int, ...], after: tuple[int, ...]) -> bytes:
    """A TIFF of ``codes`` (parameters in its description) with a transparency-mask page
    (:func:`write_mask`) per entry of ``before`` and ``after`` (its NewSubfileType),
    written before and after the image."""
    buffer = io.BytesIO()
    with tifffile.TiffWriter(buffer) as tif:
        for kind in before:
            write_mask(tif, codes.shape, kind)
        tif.write(codes, description=PARAMS_8.model_dump_json(), metadata=None)
        for kind in after:
            write_mask(tif, codes.shape, kind)
    return buffer.getvalue()


@pytest.mark.parametrize(
    ("before", "after"), [((), (4,)), ((), (5,)), ((), (4, 5)), ((4,), ()), ((5,), (4,))]
)
def test_a_tiff_frame_with_a_transparency_mask_is_read_as_its_image(
    before: tuple[int, ...], after: tuple[int, ...]
) -> None:
    """A transparency-mask page (NewSubfileType bit 2, with bit 0 or not) is not a
    frame: a frame with the 1-bit mask some editors write after it was refused as "more
    than one page of full resolution"."""
    codes = random_codes((16, 12), 8)
    frame = decode_frame(with_masks(codes, before, after), "tiff")
    np.testing.assert_array_equal(frame.codes, codes)
    assert frame.params == PARAMS_8


def test_a_tiff_of_a_mask_only_is_refused_as_holding_no_image() -> None:
    buffer = io.BytesIO()
    tifffile.imwrite(buffer, np.ones((4, 4), np.bool_), subfiletype=4, photometric="mask")
    with pytest.raises(InvalidInputError, match="only reduced-resolution pages and transparency"):
        decode_frame(buffer.getvalue(), "tiff", {"encoding": "modulo", "bits": 8})


@pytest.mark.parametrize("fmt", FRAME_FORMATS)
def test_pixel_limit(fmt: str) -> None:
    data = encode_frame(random_codes((16, 8), 8), PARAMS_8, fmt)
    overrides = {"encoding": "modulo", "bits": 8}
    assert decode_frame(data, fmt, overrides, max_pixels=128).codes.shape == (16, 8)
    with pytest.raises(ImageTooLargeError, match="16 = 128 pixels") as err:
        decode_frame(data, fmt, overrides, max_pixels=127)
    assert err.value.http_status == 413


def test_pixel_limit_is_checked_before_pixel_data() -> None:
    """A header claiming a huge image is refused as too large, not decoded or read as truncated."""
    with pytest.raises(ImageTooLargeError):
        decode_frame(png_header_only(5000, 5000), "png", max_pixels=4096 * 4096)
    header = io.BytesIO()
    np.lib.format.write_array_header_1_0(
        header, {"descr": "<u2", "fortran_order": False, "shape": (60_000, 60_000)}
    )
    with pytest.raises(ImageTooLargeError):
        decode_frame(header.getvalue(), "npy", max_pixels=10**6)


@pytest.mark.parametrize("max_pixels", [4096 * 4096, None])
def test_png_past_the_readers_bomb_limit_names_its_size(max_pixels: int | None) -> None:
    """A PNG header claiming more pixels than Pillow opens (20000^2, past its decompression
    bomb limit) names its size and the limit, as a smaller one does, not "too large to
    decode safely" with nothing to act on."""
    with pytest.raises(ImageTooLargeError, match=r"20000 x 20000 = 400000000 pixels") as err:
        decode_frame(png_header_only(20_000, 20_000), "png", max_pixels=max_pixels)
    assert "send a smaller image" in err.value.message


def test_a_png_of_colour_profiles_inflating_past_the_bound_is_refused() -> None:
    """Pillow inflated every iCCP chunk (1 MiB each at most, without a bound in all):
    a 1 MB PNG of 8 x 8 pixels and 1000 such chunks of 1 KB inflated 1 GB, in 4 s of an
    API decode slot, and was read."""
    profile = png_chunk(b"iCCP", b"icc\0\0" + zlib.compress(bytes(METADATA_BYTES // 2), 9))
    png = encode_frame(np.zeros((8, 8), np.uint8), PARAMS_8, "png")
    ihdr_end = len(PNG_SIGNATURE) + 12 + 13  # IHDR: length, type, 13 bytes, CRC
    data = png[:ihdr_end] + profile * 3 + png[ihdr_end:]
    with pytest.raises(ImageTooLargeError, match="compressed metadata .* inflates to more"):
        decode_frame(data, "png")


def test_decode_raw_known_bytes() -> None:
    eight = decode_raw(bytes([0, 1, 2, 3, 4, 5]), width=3, height=2, channels=1, bits=8)
    np.testing.assert_array_equal(eight, [[0, 1, 2], [3, 4, 5]])
    assert eight.dtype == np.uint8
    sixteen = decode_raw(b"\x01\x02\xff\x0f", width=2, height=1, channels=1, bits=12)
    np.testing.assert_array_equal(sixteen, [[0x0201, 0x0FFF]])
    assert sixteen.dtype == np.uint16
    colour = decode_raw(bytes(range(24)), width=4, height=2, channels=3, bits=8)
    assert colour.shape == (2, 4, 3)
    assert colour[1, 0, 2] == 14


def test_decode_raw_errors() -> None:
    with pytest.raises(InvalidInputError, match="12 bytes"):
        decode_raw(bytes(11), width=3, height=2, channels=1, bits=12)
    with pytest.raises(InvalidInputError, match="2\\^10"):
        decode_raw(b"\xff\xff", width=1, height=1, channels=1, bits=10)
    with pytest.raises(InvalidInputError, match="positive"):
        decode_raw(b"", width=0, height=2, channels=1, bits=8)
    with pytest.raises(InvalidInputError, match="1..16"):
        decode_raw(b"\x00", width=1, height=1, channels=1, bits=17)


@pytest.mark.parametrize("channels", [1, 2, 4])
def test_a_tiff_frame_of_one_or_other_channel_counts_is_written(channels: int) -> None:
    """H x W x 1 codes (an npy frame's, given back as TIFF by a job's result) raised
    tifffile's ValueError: the contiguous layout asked for does not fit one sample.
    They come back H x W, one grey page."""
    codes = random_codes((5, 4, channels), 8)
    back = decode_frame(encode_frame(codes, PARAMS_8, "tiff"), "tiff")
    np.testing.assert_array_equal(back.codes, codes[:, :, 0] if channels == 1 else codes)


def test_a_separate_plane_rgb_tiff_is_read_samples_last() -> None:
    rgb = random_codes((3, 6, 5), 8)
    buffer = io.BytesIO()
    tifffile.imwrite(
        buffer, rgb, photometric="rgb", planarconfig="separate",
        description=PARAMS_8.model_dump_json(), metadata=None,
    )  # fmt: skip
    frame = decode_frame(buffer.getvalue(), "tiff")
    np.testing.assert_array_equal(frame.codes, np.moveaxis(rgb, 0, -1))


def test_a_tiff_of_many_samples_a_pixel_is_refused_from_its_header() -> None:
    """1000 zlib-compressed samples a pixel: a small upload that decoded into hundreds
    of MB before the channel count was checked."""
    buffer = io.BytesIO()
    tifffile.imwrite(buffer, np.zeros((256, 256, 1000), np.uint8), photometric="minisblack",
                     planarconfig="contig", compression="zlib", metadata=None)
    assert len(buffer.getvalue()) < 2**20
    tracemalloc.start()
    try:
        with pytest.raises(ImageTooLargeError, match="holds 65536000 samples"):
            decode_frame(buffer.getvalue(), "tiff", PARAMS_8.model_dump(), 512 * 512)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert peak < 16 * 2**20, f"{peak / 2**20:.0f} MiB decoded before the refusal"


@pytest.mark.parametrize(("compression", "named"), [("tiff_lzw", "LZW"), ("zstd", "ZSTD")])
def test_an_undecoded_tiff_compression_is_refused_as_unsupported_not_damage(
    compression: str, named: str
) -> None:
    """A Zstandard TIFF (Pillow writes one) was 'truncated or corrupt (No module named
    'compression')', a 422, on Python 3.11; it is a 415 naming what is accepted."""
    buffer = io.BytesIO()
    Image.fromarray(random_codes((6, 5), 8)).save(buffer, "TIFF", compression=compression)
    with pytest.raises(UnsupportedFormatError, match=f"compression {named} .*deflate") as caught:
        decode_frame(buffer.getvalue(), "tiff", PARAMS_8.model_dump())
    assert caught.value.http_status == 415


@pytest.mark.parametrize(
    ("stored", "name", "shown"),
    [('"bits": true', "bits", "true"), ('"bits": 8, "gain": true', "gain", "true"),
     ('"bits": "8"', "bits", '"8"'), ('"bits": 8, "seed": [1]', "seed", "[1]")],
)  # fmt: skip
def test_a_tiff_storing_a_parameter_as_no_number_names_it(
    stored: str, name: str, shown: str
) -> None:
    """A JSON true was validated as 1: ``"bits": true`` refused the frame as "not 1-bit",
    ``"gain": true`` decoded it with a gain of 1."""
    buffer = io.BytesIO()
    description = '{"encoding": "modulo", ' + stored + "}"
    tifffile.imwrite(buffer, random_codes((4, 4), 8), description=description)
    problem = rf"ImageDescription stores {name} as {re.escape(shown)}, not a number"
    with pytest.raises(InvalidInputError, match=problem):
        decode_frame(buffer.getvalue(), "tiff")
    given = decode_frame(buffer.getvalue(), "tiff", {"encoding": "modulo", "bits": 8})
    assert (given.params.bits, given.params.gain) == (8, None)


def test_8_bit_codes_read_as_16_bit_are_warned_about(caplog: pytest.LogCaptureFixture) -> None:
    eight_bit = encode_frame(random_codes((6, 5), 8), None, "npy")
    decode_frame(eight_bit, "npy", {"encoding": "modulo", "bits": 16})
    assert "every code is below 256 although bits is 16" in caplog.text
    caplog.clear()
    decode_frame(eight_bit, "npy", {"encoding": "modulo", "bits": 8})
    assert caplog.text == ""


def test_a_corrupt_npy_header_is_reported_without_memory_addresses() -> None:
    """numpy quotes its header parser's nodes, with their addresses in the server."""
    header = b"{'descr': '<u1', 'fortran_order': False, 'shape': (2+2, 4), }"
    header += b" " * (118 - len(header)) + b"\n"
    data = b"\x93NUMPY\x01\x00" + len(header).to_bytes(2, "little") + header + bytes(16)
    with pytest.raises(InvalidInputError, match="truncated or corrupt") as caught:
        decode_frame(data, "npy", PARAMS_8.model_dump())
    assert " at 0x" not in caught.value.message


@pytest.mark.parametrize(
    ("content", "name"),
    [(content, name) for content in FRAME_FORMATS for name in FRAME_FORMATS if content != name],
)
def test_a_frame_is_decoded_by_its_content_whatever_its_name(
    tmp_path: Path, content: str, name: str, caplog: pytest.LogCaptureFixture
) -> None:
    """A PNG named .tiff was called a corrupt TIFF ('not a TIFF file: header=b'\\x89PNG''):
    each format is decoded as what its leading bytes show, with a warning naming both."""
    codes = random_codes((6, 5), 8)
    path = tmp_path / f"frame.{name}"
    path.write_bytes(encode_frame(codes, PARAMS_8, content))
    frame = read_frame(path, PARAMS_8.model_dump())
    np.testing.assert_array_equal(frame.codes, codes)
    assert f"content is {content.upper()} although its name or declared format says " \
        f"{name.upper()}" in caplog.text


def test_a_bigtiff_is_known_by_its_leading_bytes() -> None:
    buffer = io.BytesIO()
    tifffile.imwrite(buffer, random_codes((6, 5), 8), bigtiff=True)
    frame = decode_frame(buffer.getvalue(), "png", PARAMS_8.model_dump())
    assert frame.codes.shape == (6, 5)


@pytest.mark.parametrize(
    ("data", "fragments"),
    [
        (b"v/1\x01" + bytes(60), ("an OpenEXR image", "mcam simulate", "POST /v1/simulate")),
        (b"#?RADIANCE\n" + bytes(60), ("a Radiance HDR image", "POST /v1/simulate")),
        (b"PK\x03\x04" + bytes(60), ("a zip", "mcam video", "POST /v1/videos")),
    ],
    ids=["exr", "radiance", "zip"],
)
def test_an_hdr_image_or_a_zip_named_as_a_frame_is_pointed_to_its_command(
    data: bytes, fragments: tuple[str, ...]
) -> None:
    """Named .png, they were 'not a PNG image (bad or missing signature)'."""
    with pytest.raises(UnsupportedFormatError, match="not a wrapped frame") as caught:
        decode_frame(data, "png", PARAMS_8.model_dump())
    assert all(fragment in caught.value.message for fragment in fragments)
