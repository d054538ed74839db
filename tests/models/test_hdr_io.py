"""Tests of models/hdr_io.py (OpenEXR read/write) and models/radiance.py (Radiance RGBE)."""

from __future__ import annotations

import io
import os
import re
from collections.abc import Callable
from pathlib import Path

import numpy as np
import OpenEXR
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from models import radiance
from models.errors import (
    ImageTooLargeError,
    InvalidInputError,
    OutputOverflowError,
    OutputUnderflowError,
    UnsupportedFormatError,
)
from models.hdr_io import (
    EXR_COMPRESSIONS,
    HdrImage,
    encode_exr,
    read_hdr,
    write_exr,
)
from models.radiance import MAX_RADIANCE_HEADER, rgbe_to_float, smallest_scanline

HDRI = Path(__file__).resolve().parents[2] / "models" / "data" / "hdri" / "lab.exr"
RADIANCE_HEADER = b"#?RADIANCE\n# made by hand\nFORMAT=32-bit_rle_rgbe\nEXPOSURE=1.0\n\n"


def exr_header() -> dict[str, object]:
    """A fresh header: OpenEXR.File fills in the dict it is given."""
    return {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}


def smooth_rgb(height: int = 12, width: int = 10) -> np.ndarray:
    yy, xx = np.mgrid[0:height, 0:width]
    base = np.exp(-((yy - 5.0) ** 2 + (xx - 4.0) ** 2) / 20.0) * 1000.0 + 0.01
    return np.stack([base, base * 0.5, base * 0.25], axis=2)


def exr_parts(path: Path, *parts: tuple[str, dict[str, np.ndarray]]) -> Path:
    OpenEXR.File([OpenEXR.Part(exr_header(), ch, name) for name, ch in parts]).write(str(path))
    return path


def rle_component(values: np.ndarray) -> bytes:
    """Radiance new-style RLE of one component: runs of >= 3 equal bytes, else literals."""
    out, i, n = bytearray(), 0, len(values)
    while i < n:
        run = 1
        while i + run < n and run < 127 and values[i + run] == values[i]:
            run += 1
        if run >= 3:
            out += bytes([128 + run, int(values[i])])
            i += run
            continue
        start = i
        while i < n and i - start < 128:
            if i + 2 < n and values[i] == values[i + 1] == values[i + 2]:
                break
            i += 1
        out += bytes([i - start]) + bytes(values[start:i].astype(np.uint8))
    return bytes(out)


def radiance_rle(rgbe: np.ndarray, orientation: str = "-Y") -> bytes:
    """A Radiance file of ``rgbe`` (H x W x 4) with every scanline new-style RLE."""
    height, width, _ = rgbe.shape
    body = bytearray(RADIANCE_HEADER + f"{orientation} {height} +X {width}\n".encode())
    for row in rgbe:
        body += bytes([2, 2, width >> 8, width & 0xFF])
        for component in range(4):
            body += rle_component(row[:, component])
    return bytes(body)


# A hand-built 2 x 8 file: row 0 new-style RLE, row 1 flat.
HAND_ROW0 = (
    bytes([2, 2, 0, 8])
    + bytes([128 + 8, 128])  # R: a run of eight 128s
    + bytes([8, 0, 10, 20, 30, 40, 50, 60, 70])  # G: eight literals
    + bytes([128 + 8, 0])  # B: a run of zeros
    + bytes([128 + 4, 129, 4, 130, 130, 131, 0])  # E: run of four 129s, four literals
)
HAND_ROW1 = bytes([255, 0, 0, 136] + [1, 2, 3, 0] * 7)
HAND_FILE = RADIANCE_HEADER + b"-Y 2 +X 8\n" + HAND_ROW0 + HAND_ROW1


def test_exr_round_trip_rgb_and_gray(tmp_path: Path) -> None:
    rgb = smooth_rgb()
    write_exr(tmp_path / "rgb.exr", rgb, {"encoding": "mantissa", "alpha": "2.0"})
    image = read_hdr(tmp_path / "rgb.exr")
    assert isinstance(image, HdrImage)
    assert image.pixels.dtype == np.float64
    assert image.pixels.shape == rgb.shape
    np.testing.assert_array_equal(image.pixels, rgb.astype(np.float32))
    assert image.attributes["encoding"] == "mantissa"
    assert image.attributes["alpha"] == "2.0"
    assert re.fullmatch(r"\d{4}:\d\d:\d\d \d\d:\d\d:\d\d", image.attributes["capDate"])
    assert image.attributes["comments"]
    assert image.negatives_clipped == 0
    gray = read_hdr(encode_exr(rgb[:, :, 0], {"comments": "blob"}))
    assert gray.pixels.shape == rgb.shape[:2]
    assert gray.attributes["comments"] == "blob"
    header = OpenEXR.File(str(tmp_path / "rgb.exr"), header_only=True).header()
    assert sorted(ch.name for ch in header["channels"]) == ["B", "G", "R"]


def test_exr_single_channel_is_written_as_y(tmp_path: Path) -> None:
    write_exr(tmp_path / "y.exr", smooth_rgb()[:, :, :1])
    header = OpenEXR.File(str(tmp_path / "y.exr"), header_only=True).header()
    assert [ch.name for ch in header["channels"]] == ["Y"]


@settings(max_examples=30, deadline=None)
@given(arrays(np.float64, (3, 4), elements=st.just(0.0) | st.floats(2.0**-24, 6e4)))
def test_exr_half_round_trip_within_half_precision(values: np.ndarray) -> None:
    back = read_hdr(encode_exr(values, half=True)).pixels
    np.testing.assert_allclose(back, values, rtol=2.0**-11, atol=2.0**-24)
    np.testing.assert_array_equal(back, values.astype(np.float16))


def exr_compression_of(data: bytes) -> object:
    """The compression an EXR file's header names."""
    return OpenEXR.File(io.BytesIO(data), header_only=True).header()["compression"]


@settings(max_examples=20, deadline=None)
@given(
    arrays(np.float64, (5, 7), elements=st.just(0.0) | st.floats(2.0**-149, 3e38)),
    st.sampled_from(sorted(EXR_COMPRESSIONS)),
)
def test_every_compression_is_lossless_and_named_in_the_header(
    values: np.ndarray, compression: str
) -> None:
    data = encode_exr(values, compression=compression)
    assert exr_compression_of(data) == EXR_COMPRESSIONS[compression]
    np.testing.assert_array_equal(read_hdr(data).pixels, values.astype(np.float32))


def test_uncompressed_exr_is_larger_and_written_to_files(tmp_path: Path) -> None:
    rgb = smooth_rgb()
    write_exr(tmp_path / "plain.exr", rgb, compression="none")
    plain = (tmp_path / "plain.exr").read_bytes()
    assert exr_compression_of(plain) == OpenEXR.NO_COMPRESSION
    assert len(plain) > len(encode_exr(rgb))
    np.testing.assert_array_equal(read_hdr(plain).pixels, rgb.astype(np.float32))


def test_unknown_compression_names_the_choices() -> None:
    with pytest.raises(InvalidInputError, match="unknown EXR compression 'lzw'.*zip, none"):
        encode_exr(np.ones((2, 2)), compression="lzw")


def test_half_and_float32_overflow_are_errors() -> None:
    with pytest.raises(OutputOverflowError, match="2 pixels.*float16"):
        encode_exr(np.array([[1.0, 7e4], [1e5, 3.0]]), half=True)
    assert read_hdr(encode_exr(np.array([[1.0, 7e4]]))).pixels[0, 1] == 7e4
    with pytest.raises(OutputOverflowError, match="float32"):
        encode_exr(np.array([[1.0, 1e39]]))
    with pytest.raises(OutputOverflowError, match="1 pixels.*float32 limit"):
        encode_exr(np.array([[1.0, -np.inf]]))
    with pytest.raises(InvalidInputError, match="^1 pixels of the HDR image are NaN"):
        encode_exr(np.array([[1.0, np.nan]]))


def test_nonzero_values_the_pixel_type_would_store_as_zero_are_errors() -> None:
    """They were written as 0 in silence: a reference image gone black."""
    with pytest.raises(OutputUnderflowError, match="1 nonzero pixels.*float16.*float32"):
        encode_exr(np.array([[1.0, 1e-9]]), half=True)
    with pytest.raises(OutputUnderflowError, match="2 nonzero pixels.*gain 1e\\+50"):
        encode_exr(np.array([[1e-46, 4e-50]]), scene_gain=1e50)
    assert read_hdr(encode_exr(np.array([[0.0, 1e-9]]))).pixels[0, 1] == np.float32(1e-9)


@pytest.mark.parametrize("shape", [(0, 4), (4,), (3, 3, 2), (2, 2, 4)])
def test_encode_exr_rejects_bad_shapes(shape: tuple[int, ...]) -> None:
    with pytest.raises(InvalidInputError, match="H x W"):
        encode_exr(np.ones(shape))


def test_multi_part_exr_reads_the_first_image_part(tmp_path: Path) -> None:
    rgb = smooth_rgb().astype(np.float32)
    depth = np.ones(rgb.shape[:2], np.float32)
    planes = {name: np.ascontiguousarray(rgb[:, :, i]) for i, name in enumerate("RGB")}
    path = exr_parts(tmp_path / "multi.exr", ("depth", {"Z": depth}), ("beauty", planes))
    np.testing.assert_array_equal(read_hdr(path).pixels, rgb)
    gray = exr_parts(tmp_path / "gray.exr", ("luma", {"Y": depth * 5}), ("beauty", planes))
    np.testing.assert_array_equal(read_hdr(gray).pixels, depth * 5)
    nothing = exr_parts(tmp_path / "none.exr", ("depth", {"Z": depth}), ("mask", {"A": depth}))
    with pytest.raises(UnsupportedFormatError, match="A, Z"):
        read_hdr(nothing)


def test_bytes_and_path_read_the_same(tmp_path: Path) -> None:
    path = tmp_path / "scene.exr"
    write_exr(path, smooth_rgb())
    np.testing.assert_array_equal(read_hdr(path.read_bytes()).pixels, read_hdr(path).pixels)


@pytest.mark.parametrize("kind", ["exr", "hdr"])
def test_a_pipe_is_read_as_its_file(kind: str) -> None:
    """A pipe (``mcam simulate <(gunzip -c s.exr.gz)``) was opened once for its leading
    bytes and again to decode, which found them gone: "the OpenEXR header is truncated
    or corrupt". Small files: the pipe holds them whole before they are read."""
    pixels = smooth_rgb(4, 5)
    if kind == "exr":
        data = encode_exr(pixels)
    else:
        rgbe = np.full((4, 5, 4), 128, np.uint8)
        data = RADIANCE_HEADER + b"-Y 4 +X 5\n" + rgbe.tobytes()
    read, write = os.pipe()
    try:
        os.write(write, data)
        os.close(write)
        image = read_hdr(f"/dev/fd/{read}")
    finally:
        os.close(read)
    np.testing.assert_array_equal(image.pixels, read_hdr(data).pixels)


def test_truncated_and_foreign_files(tmp_path: Path, capfd: pytest.CaptureFixture[str]) -> None:
    """A truncated upload is refused with the reason, and the OpenEXR library, which
    prints its complaints to the process's stderr, never sees it."""
    data = encode_exr(np.random.default_rng(0).random((64, 64, 3)))
    for cut in (len(data) // 2, len(data) - 8, 40):
        with pytest.raises(InvalidInputError, match="upload.exr: .*truncated or corrupt"):
            read_hdr(data[:cut], name="upload.exr")
    assert capfd.readouterr().err == ""
    with pytest.raises(UnsupportedFormatError, match="OpenEXR or Radiance"):
        read_hdr(b"GIF89a" + bytes(100))
    with pytest.raises(FileNotFoundError):
        read_hdr(tmp_path / "missing.exr")


def test_pixel_limit() -> None:
    data = encode_exr(np.ones((8, 16)))
    assert read_hdr(data, max_pixels=128).pixels.shape == (8, 16)
    with pytest.raises(ImageTooLargeError, match="128 pixels"):
        read_hdr(data, max_pixels=127)
    with pytest.raises(ImageTooLargeError):
        read_hdr(HAND_FILE, max_pixels=15)


def test_negative_nan_and_clipping() -> None:
    values = np.ones((4, 4))
    values[0, :3] = -0.5
    data = encode_exr(values)
    with pytest.raises(InvalidInputError, match="3 negative.*--clip-negative"):
        read_hdr(data)
    clipped = read_hdr(data, clip_negative=True)
    assert clipped.negatives_clipped == 3
    assert clipped.pixels.min() == 0.0
    infinite = np.ones((2, 2), np.float32)
    infinite[1, 1] = np.inf
    buffer = io.BytesIO()
    OpenEXR.File(exr_header(), {"Y": infinite}).write(buffer)
    with pytest.raises(InvalidInputError, match="1 NaN or infinite"):
        read_hdr(buffer.getvalue())


def test_real_lossy_hdri_needs_clipping() -> None:
    with pytest.raises(InvalidInputError, match="negative"):
        read_hdr(HDRI)
    image = read_hdr(HDRI, clip_negative=True)
    assert image.pixels.shape == (256, 512, 3)
    assert image.negatives_clipped > 0
    assert image.pixels.max() > 1.0


def test_hand_built_radiance_file_known_values() -> None:
    image = read_hdr(HAND_FILE, name="hand.hdr")
    assert image.pixels.shape == (2, 8, 3)
    assert image.attributes == {"FORMAT": "32-bit_rle_rgbe", "EXPOSURE": "1.0"}
    # (128, 0, 0, e=129): R = 128.5 * 2^-7, G = B = 0.5 * 2^-7.
    np.testing.assert_array_equal(image.pixels[0, 0], [1.00390625, 0.00390625, 0.00390625])
    # (128, 70, 0, e=0) is black.
    np.testing.assert_array_equal(image.pixels[0, 7], [0.0, 0.0, 0.0])
    # (128, 50, 0, e=130): 2^-6 * (128.5, 50.5, 0.5); (128, 60, 0, e=131): 2^-5 * (...).
    np.testing.assert_array_equal(image.pixels[0, 5], [2.0078125, 0.7890625, 0.0078125])
    np.testing.assert_array_equal(image.pixels[0, 6], [4.015625, 1.890625, 0.015625])
    # flat row: (255, 0, 0, e=136) -> 255.5; (1, 2, 3, e=0) -> black.
    np.testing.assert_array_equal(image.pixels[1, 0], [255.5, 0.5, 0.5])
    np.testing.assert_array_equal(image.pixels[1, 1:], 0.0)


@settings(max_examples=20, deadline=None)
@given(
    height=st.integers(1, 6),
    width=st.integers(8, 300),
    seed=st.integers(0, 2**16),
    flat_fraction=st.floats(0, 1),
)
def test_radiance_rle_round_trip(height: int, width: int, seed: int, flat_fraction: float) -> None:
    rng = np.random.default_rng(seed)
    rgbe = rng.integers(0, 256, (height, width, 4)).astype(np.uint8)
    runs = rng.random((height, width)) < flat_fraction
    rgbe[runs] = rgbe[0, 0]
    image = read_hdr(radiance_rle(rgbe))
    np.testing.assert_array_equal(image.pixels, rgbe_to_float(rgbe))


def test_radiance_orientation_flips_rows() -> None:
    rgbe = np.random.default_rng(1).integers(1, 256, (3, 9, 4)).astype(np.uint8)
    bottom_up = read_hdr(radiance_rle(rgbe, orientation="+Y")).pixels
    np.testing.assert_array_equal(bottom_up, rgbe_to_float(rgbe)[::-1])


#: Scanlines of a 4 x 300 file, each a list of components (R, G, B, E) of segments:
#: +n a literal of n bytes, -n a run of n equal bytes (None: the scanline is flat).
#: Components and scanlines end on a run or a literal, runs and literals of one pixel
#: and of the most a count holds (127 and 128) sit next to every boundary.
SEGMENTS = (
    ([128, 45, -127], [-127, -127, 46], [1, -1, 128, -127, 43], [-100, 100, -100]),
    ([-127, 128, 45], [-1, 1, -1, 128, 128, 41], [-127, -127, -46], [-127, -45, 128]),
    None,
    ([1, -127, 1, -127, 44], [100, -100, 100], [128, 128, 44], [-127, -127, -46]),
)
SEGMENTS_WIDTH = 300


def segmented_radiance(seed: int = 5) -> tuple[bytes, np.ndarray, list[int]]:
    """The file of :data:`SEGMENTS` with random bytes, its RGBE pixels (H x W x 4), and
    the byte offset where each scanline ends."""
    rng = np.random.default_rng(seed)
    height, width = len(SEGMENTS), SEGMENTS_WIDTH
    rgbe = np.zeros((height, width, 4), np.uint8)
    body = bytearray(RADIANCE_HEADER + f"-Y {height} +X {width}\n".encode())
    ends = []
    for row, components in enumerate(SEGMENTS):
        if components is None:
            rgbe[row] = rng.integers(3, 256, (width, 4))  # no RLE start, no old-style run
            body += rgbe[row].tobytes()
            ends.append(len(body))
            continue
        body += bytes([2, 2, width >> 8, width & 0xFF])
        for component, segments in enumerate(components):
            values = bytearray()
            for n in segments:
                chunk = rng.integers(0, 256, abs(n)).astype(np.uint8).tobytes()
                if n < 0:
                    chunk = chunk[:1] * -n
                    body += bytes([128 - n, chunk[0]])
                else:
                    body += bytes([n]) + chunk
                values += chunk
            rgbe[row, :, component] = np.frombuffer(bytes(values), np.uint8)
        ends.append(len(body))
    return bytes(body), rgbe, ends


@pytest.mark.parametrize("rows_per_block", [None, 1, 2])
def test_radiance_runs_and_literals_at_scanline_boundaries(
    monkeypatch: pytest.MonkeyPatch, rows_per_block: int | None
) -> None:
    """Runs and literals ending components and scanlines, a flat scanline between RLE
    ones, and the reader's blocks of scanlines ending anywhere (every scanline, every
    second one, or all in one block) give the pixels exactly."""
    if rows_per_block is not None:
        monkeypatch.setattr(radiance, "_BLOCK_BYTES", rows_per_block * 4 * SEGMENTS_WIDTH)
    data, rgbe, _ = segmented_radiance()
    np.testing.assert_array_equal(read_hdr(data).pixels, rgbe_to_float(rgbe))


@pytest.mark.parametrize(
    ("broken", "row"),
    [
        (lambda data, ends: data[: ends[0]], 1),
        (lambda data, ends: data[: ends[1] - 1], 1),
        (lambda data, ends: data[: ends[3] - 1], 3),
        (lambda data, ends: data[: ends[2] + 4] + b"\x00" + data[ends[2] + 5 :], 3),
    ],
    ids=["cut-after-scanline-0", "last-literal-cut", "last-run-without-value", "run-of-0"],
)
def test_radiance_cut_or_broken_at_a_scanline_boundary_names_the_scanline(
    broken: Callable[[bytes, list[int]], bytes], row: int
) -> None:
    """A file cut where a scanline ends, one whose last literal or run is cut short, and
    a count of 0 opening a scanline are refused naming the scanline at fault."""
    data, _, ends = segmented_radiance()
    with pytest.raises(InvalidInputError, match=f"corrupt at scanline {row};"):
        read_hdr(broken(data, ends))


def test_rgbe_to_float_is_the_bin_centre() -> None:
    rgbe = np.array([[0, 0, 0, 0], [255, 127, 0, 128], [1, 1, 1, 1]], np.uint8)
    expected = np.array([[0, 0, 0], [255.5 / 256, 127.5 / 256, 0.5 / 256], [1.5, 1.5, 1.5]])
    expected[2] *= 2.0**-135
    np.testing.assert_array_equal(rgbe_to_float(rgbe), expected)


def test_broken_radiance_files() -> None:
    for cut in (len(HAND_FILE) - 1, len(HAND_FILE) - len(HAND_ROW1) - 3):
        with pytest.raises(InvalidInputError, match="truncated or corrupt"):
            read_hdr(HAND_FILE[:cut])
    overlong_run = HAND_FILE.replace(bytes([128 + 8, 128]), bytes([128 + 9, 128]), 1)
    with pytest.raises(InvalidInputError, match="scanline 0"):
        read_hdr(overlong_run)
    with pytest.raises(InvalidInputError, match="blank line"):
        read_hdr(b"#?RADIANCE\nFORMAT=32-bit_rle_rgbe\n")
    with pytest.raises(UnsupportedFormatError, match="xyze"):
        read_hdr(HAND_FILE.replace(b"rle_rgbe", b"rle_xyze"))
    with pytest.raises(UnsupportedFormatError, match="resolution"):
        read_hdr(HAND_FILE.replace(b"-Y 2 +X 8", b"+X 8 -Y 2"))
    with pytest.raises(InvalidInputError, match="width 9"):
        read_hdr(HAND_FILE.replace(bytes([2, 2, 0, 8]), bytes([2, 2, 0, 9])))


def test_a_radiance_header_larger_than_its_data_is_refused_before_allocating() -> None:
    """100000 x 100000 declared over no data: refused from the file length (was a
    MemoryError allocating 40 GB)."""
    header = b"#?RADIANCE\nFORMAT=32-bit_rle_rgbe\n\n-Y 100000 +X 100000\n"
    with pytest.raises(InvalidInputError, match="declares 100000 x 100000 pixels.* 0 bytes follow"):
        read_hdr(header)
    assert smallest_scanline(8) == 4 + 8 and smallest_scanline(128) == 4 + 16
    assert smallest_scanline(7) == 28  # too narrow for RLE: flat


def test_a_radiance_header_over_its_limit_is_refused_before_it_is_split() -> None:
    """A 65 MB header of 6 million ``aN=b`` lines was split and read (+1.1 GB, 4-11 s)."""
    pixel = b"-Y 1 +X 1\n" + bytes([128, 128, 128, 129])

    def with_variables(count: int) -> bytes:
        return RADIANCE_HEADER[:-1] + b"a=bcdef\n" * count + b"\n" + pixel

    under = (MAX_RADIANCE_HEADER - len(RADIANCE_HEADER)) // 8
    assert read_hdr(with_variables(under)).attributes["a"] == "bcdef"
    with pytest.raises(ImageTooLargeError, match=f"header runs past {MAX_RADIANCE_HEADER} bytes"):
        read_hdr(with_variables(under + 1))
    with pytest.raises(InvalidInputError, match="no blank line"):
        read_hdr(RADIANCE_HEADER[:-1])


def test_attribute_text_utf8_cannot_hold_is_escaped() -> None:
    """A file name that is not UTF-8 (a byte 0xff, surrogate-escaped) in ``comments``
    crashed ``mcam reconstruct`` with UnicodeEncodeError."""
    name = os.fsdecode(b"frame_\xff.png")
    data = encode_exr(np.ones((2, 2)), {"comments": f"of {name}", "owner": "x\ud800 café"})
    attributes = read_hdr(data).attributes
    assert attributes["comments"] == "of frame_\\xff.png"
    assert attributes["owner"] == "x\\ud800 café"


@pytest.mark.parametrize(
    ("resolution", "row"),
    [
        (b"-Y 3 +X 10\n", bytes([128, 64, 32, 129, 1, 1, 1, 9])),  # shorter than flat
        (b"-Y 2 +X 2\n", bytes([128, 64, 32, 129, 1, 1, 1, 1])),  # as long as flat
    ],
    ids=["compressed", "width-2"],
)
def test_old_style_radiance_runs_are_refused(resolution: bytes, row: bytes) -> None:
    """A pixel then (1, 1, 1, n), "repeat it n times": was read as a flat pixel
    (1, 1, 1, e), or refused as truncated when the runs made the file shorter."""
    with pytest.raises(UnsupportedFormatError, match=r"old-style run-length .*\(scanline 0\)"):
        read_hdr(RADIANCE_HEADER + resolution + row * 3)


def test_header_text_that_is_not_utf8_is_named() -> None:
    """A valid file with a Latin-1 attribute was refused as 'truncated or corrupt'."""
    buffer = io.BytesIO()
    header = exr_header() | {"owner": "Rene"}
    OpenEXR.File(header, {"Y": np.ones((2, 2), np.float32)}).write(buffer)
    latin1 = buffer.getvalue().replace(b"Rene", b"Ren\xe9")
    with pytest.raises(UnsupportedFormatError, match=r"not UTF-8: byte 0xe9 in b'Ren\\xe9'"):
        read_hdr(latin1)


@pytest.mark.parametrize(
    ("head", "fmt"), [(b"\x89PNG\r\n\x1a\n", "PNG"), (b"II*\x00", "TIFF"), (b"\x93NUMPY", "NPY")],
    ids=["png", "tiff", "npy"],
)
def test_a_wrapped_frame_given_as_an_hdr_image_is_pointed_to_the_reconstructions(
    head: bytes, fmt: str
) -> None:
    """It got only 'not an OpenEXR or Radiance HDR image; convert it to OpenEXR'."""
    with pytest.raises(UnsupportedFormatError) as caught:
        read_hdr(head + bytes(100), name="frame.exr")
    assert caught.value.message.startswith(f"frame.exr: a {fmt} file, not an OpenEXR")
    assert "mcam reconstruct or POST /v1/reconstructions" in caught.value.message
