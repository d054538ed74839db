"""Tests of worker/video_output.py: HDR10 HEVC, SDR preview and EXR sequence, read back."""

from __future__ import annotations

import io
import warnings
import zipfile
from fractions import Fraction

import av
import numpy as np
import OpenEXR
import pytest
from av.sidedata.sidedata import Type
from hypothesis import given
from hypothesis import strategies as st

from models.errors import InvalidInputError, OutputUnderflowError
from models.hdr_io import EXR_COMPRESSIONS, read_hdr
from tests.worker.conftest import count_calls
from worker import video_output
from worker.video_output import (
    BT709_TO_BT2020,
    LUMA_OFFSET,
    LUMA_SCALE,
    REFERENCE_WHITE,
    Hdr10Settings,
    add_hdr10_stream,
    check_mp4_frame_size,
    exr_sequence_zip,
    frame_rate,
    hdr10_yuv,
    light_levels,
    pq_decode,
    pq_encode,
    sdr_frames,
    to_nits,
    write_hdr10,
    write_sdr_preview,
    x265_params,
    yuv_frame,
)

FRAMES = 6


def grey_clip(height: int = 64, width: int = 96) -> list[np.ndarray]:
    """An achromatic clip from deep shadow (0.001) to far above reference white (40)."""
    ramp = np.geomspace(1e-3, 40.0, height * width).reshape(height, width)
    return [ramp * (1.0 + 0.05 * t) for t in range(FRAMES)]


def hdr10_bytes(frames: list[np.ndarray], settings: Hdr10Settings) -> tuple[bytes, object]:
    buffer = io.BytesIO()
    levels = write_hdr10(frames, buffer, settings)
    return buffer.getvalue(), levels


@given(st.floats(0.0, 10_000.0))
def test_pq_round_trip(nits: float) -> None:
    assert pq_decode(pq_encode(np.array(nits))) == pytest.approx(nits, rel=1e-9, abs=1e-9)


def test_pq_reference_values() -> None:
    """ST 2084: 10000 cd/m^2 -> 1.0; 100 cd/m^2 -> 0.5081 (BT.2100 table); monotone."""
    assert pq_encode(np.array(10_000.0)) == pytest.approx(1.0)
    assert pq_encode(np.array(100.0)) == pytest.approx(0.5081, abs=1e-4)
    assert pq_encode(np.array(20_000.0)) == pytest.approx(1.0)
    assert np.all(np.diff(pq_encode(np.geomspace(1e-3, 1e4, 100))) > 0)


def test_grey_stays_grey_in_bt2020() -> None:
    np.testing.assert_allclose(BT709_TO_BT2020.sum(axis=1), 1.0, atol=1e-12)


def test_hdr10_file_tags_metadata_and_frame_count() -> None:
    data, levels = hdr10_bytes(grey_clip(), Hdr10Settings())
    with av.open(io.BytesIO(data)) as container:
        stream = container.streams.video[0]
        context = stream.codec_context
        assert context.name == "hevc"
        assert context.pix_fmt == "yuv420p10le"
        assert context.color_trc == av.video.reformatter.ColorTrc.SMPTE2084
        assert context.color_primaries == av.video.reformatter.ColorPrimaries.BT2020
        assert context.colorspace == av.video.reformatter.Colorspace.BT2020
        frames = list(container.decode(stream))
    assert len(frames) == FRAMES
    first = frames[0]
    assert first.format.name == "yuv420p10le"
    kinds = {side.type for side in first.side_data}
    assert Type.MASTERING_DISPLAY_METADATA in kinds and Type.CONTENT_LIGHT_LEVEL in kinds
    light = next(bytes(s) for s in first.side_data if s.type == Type.CONTENT_LIGHT_LEVEL)
    max_cll, max_fall = np.frombuffer(light[:8], "<u4")
    assert (max_cll, max_fall) == (levels.max_cll, levels.max_fall)
    assert levels.max_cll == 10_000  # 40 x 1.25 x 203 cd/m^2 clipped at the PQ peak


def test_hdr10_first_frame_inverts_to_the_reconstruction() -> None:
    """Lossless HEVC of a grey clip: decoding Y', inverting PQ and the exposure scaling
    returns x within the 10-bit quantization of the PQ signal. Y' is rounded to
    1/876 of the signal (limited range), so the signal is off by at most h = 0.5/876
    and the luminance lies in [PQ^-1(E - h), PQ^-1(E + h)]: a relative bound that
    follows PQ's slope (about 0.5% mid-range). Chroma of grey is exactly 512."""
    frames = grey_clip()
    data, _ = hdr10_bytes(frames, Hdr10Settings(lossless=True))
    with av.open(io.BytesIO(data)) as container:
        planes = next(container.decode(video=0)).to_ndarray()
    height, width = frames[0].shape
    luma, chroma = planes[:height].astype(np.float64), planes[height:]
    assert np.all(chroma == 512)
    decoded = pq_decode((luma - LUMA_OFFSET) / LUMA_SCALE) / REFERENCE_WHITE
    signal, h = pq_encode(frames[0] * REFERENCE_WHITE), 0.5 / LUMA_SCALE
    low, high = pq_decode(signal - h) / REFERENCE_WHITE, pq_decode(signal + h) / REFERENCE_WHITE
    assert np.all(decoded >= low * (1 - 1e-9)) and np.all(decoded <= high * (1 + 1e-9))
    relative = np.abs(decoded / frames[0] - 1)
    assert relative[frames[0] > 0.1].max() < 0.01


def test_white_level_scales_luminance() -> None:
    frames = [np.full((64, 64), 2.0)] * 2
    _, levels = hdr10_bytes(frames, Hdr10Settings(white_level=2.0, reference_white=100.0))
    assert levels.max_cll == levels.max_fall == 100


def test_odd_sizes_are_padded() -> None:
    data, _ = hdr10_bytes([np.full((65, 67, 3), 0.5)] * 2, Hdr10Settings())
    with av.open(io.BytesIO(data)) as container:
        stream = container.streams.video[0]
        assert (stream.codec_context.width, stream.codec_context.height) == (68, 66)


@pytest.mark.parametrize("count", [1, 2, 3, 6])
def test_encoder_packets_carry_sane_decode_timestamps(count: int) -> None:
    """x265 hands out uninitialised dts for clips shorter than its B-frame delay unless
    B-frames are off (the MP4 muxer then fails at random): every packet's dts must rise,
    stay at or below its pts and lie within the clip's few frames of delay."""
    settings = Hdr10Settings()
    frames = [np.full((64, 64), 0.5 + 0.1 * t) for t in range(count)]
    with av.open(io.BytesIO(), mode="w", format="mp4") as container:
        stream = add_hdr10_stream(
            container, settings, light_levels(frames, settings), (64, 64), count
        )
        packets = [p for f in frames for p in stream.encode(yuv_frame(hdr10_yuv(f, settings)))]
        packets += stream.encode(None)
        assert len(packets) == count
        dts = [p.dts for p in packets]
        assert dts == sorted(dts) and all(-count <= t < count for t in dts)
        assert all(p.dts <= p.pts for p in packets)
        container.mux(packets)


def test_hdr10_refuses_frames_libx265_cannot_take() -> None:
    with pytest.raises(InvalidInputError, match="at least 64 x 64"):
        write_hdr10([np.ones((48, 48))] * 2, io.BytesIO())


def test_the_hdr10_size_check_counts_the_padding_of_an_odd_side() -> None:
    """63 x 63 frames are padded to 64 x 64 and encoded, so the early checks of the API
    and the CLI (which see the frame's own size) must let them through."""
    check_mp4_frame_size("hdr10", 63, 63, "")
    with pytest.raises(InvalidInputError, match="got 62 x 63"):
        check_mp4_frame_size("hdr10", 62, 63, "")
    assert write_hdr10([np.ones((63, 63))] * 2, io.BytesIO()).max_cll > 0


def test_the_mp4_videos_refuse_sides_their_encoders_cannot_take() -> None:
    """Frames within the pixel limit but wider than libx264 (16384) or an MP4 track
    (65535) encodes failed, after every frame was decoded, with "Generic error in an
    external library" or "Invalid argument"; they are refused by name, odd sides counted
    padded, and the widest side the SDR preview takes is encoded."""
    with pytest.raises(InvalidInputError, match="at most 16384 pixels a side, got 2 x 16385"):
        write_sdr_preview([np.ones((2, 16385))] * 2, io.BytesIO())
    write_sdr_preview([np.ones((2, 16384))] * 2, io.BytesIO())
    with pytest.raises(InvalidInputError, match="at most 65534 pixels a side, got 64 x 65536"):
        write_hdr10([np.ones((64, 65536))] * 2, io.BytesIO())
    check_mp4_frame_size("hdr10", 64, 65534, "")
    with pytest.raises(InvalidInputError, match="got 65535 x 64; write less"):
        check_mp4_frame_size("hdr10", 65535, 64, "write less")


def test_sdr_preview_reads_back() -> None:
    frames = grey_clip()
    buffer = io.BytesIO()
    write_sdr_preview(frames, buffer, fps=24)
    buffer.seek(0)
    with av.open(buffer) as container:
        stream = container.streams.video[0]
        assert stream.codec_context.name == "h264"
        decoded = [f.to_ndarray(format="rgb24") for f in container.decode(stream)]
    assert len(decoded) == FRAMES
    expected = next(sdr_frames(frames)).astype(int)
    assert np.abs(decoded[0].astype(int) - expected).mean() < 3


def test_sdr_tonemap_keeps_order_and_range() -> None:
    image = next(sdr_frames(grey_clip()))[:, :, 0].ravel()
    assert np.all(np.diff(image.astype(int)) >= 0) and image[0] < 10 and image[-1] > 200


def test_sdr_preview_of_a_flash_far_brighter_than_its_key_frame() -> None:
    """A mantissa clip (alpha 1e6) reached x = 2.5e305 next to a middle frame of 1e-5:
    the tonemap was NaN there and the preview (and the whole video job) was refused."""
    dark = np.full((64, 64), 1e-5)
    flash = dark.copy()
    flash[:8, :8] = 2.5e305
    images = list(sdr_frames([flash, dark, flash]))
    assert (images[0][:8, :8] == 255).all() and (images[0][8:, 8:] == images[1][8:, 8:]).all()



def test_sdr_preview_reports_each_frame_as_soon_as_it_is_tonemapped(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Every frame was tonemapped before the first was encoded: a job's progress (and a
    cancel) waited at the preview's start for 80% of its time (44 ms of 55 ms a frame at
    512 x 512)."""
    tonemapped = count_calls(monkeypatch, video_output, "reinhard")
    seen: list[tuple[int, int]] = []
    write_sdr_preview(
        grey_clip(), io.BytesIO(), progress=lambda done: seen.append((done, len(tonemapped)))
    )
    assert seen == [(n, n) for n in range(1, FRAMES + 1)]

@pytest.mark.parametrize("compression", sorted(EXR_COMPRESSIONS))
def test_exr_sequence_zip_round_trip(compression: str) -> None:
    frames = [np.random.default_rng(t).uniform(0, 20, (6, 5, 3)) for t in range(3)]
    buffer = io.BytesIO()
    exr_sequence_zip(frames, buffer, compression=compression)
    with zipfile.ZipFile(buffer) as archive:
        names = archive.namelist()
        assert names == ["frame_00000.exr", "frame_00001.exr", "frame_00002.exr"]
        for name, frame in zip(names, frames, strict=True):
            data = archive.read(name)
            image = read_hdr(data)
            np.testing.assert_array_equal(image.pixels, frame.astype(np.float32))
            header = OpenEXR.File(io.BytesIO(data), header_only=True).header()
            assert header["compression"] == EXR_COMPRESSIONS[compression]


def test_exr_names_of_a_clip_past_99999_frames_sort_in_frame_order(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """frame_100000.exr sorted before frame_10001.exr: five digits held 100000 frames."""
    monkeypatch.setattr("worker.video_output.encode_exr", lambda *_args, **_kwargs: b"")
    buffer = io.BytesIO()
    exr_sequence_zip([np.ones((1, 1))] * 100_001, buffer, checked=True)
    with zipfile.ZipFile(buffer) as archive:
        names = archive.namelist()
    assert names == sorted(names)
    assert names[0] == "frame_000000.exr" and names[-1] == "frame_100000.exr"


def test_frames_that_would_be_stored_as_zero_are_refused() -> None:
    """Scene units under a huge gain, or tiny values as half floats: no black EXRs."""
    frames = [np.full((4, 4), 2.0), np.full((4, 4), 1e-300)]
    with pytest.raises(OutputUnderflowError, match="16 nonzero pixels of the video frame 1"):
        exr_sequence_zip(frames, io.BytesIO())
    with pytest.raises(OutputUnderflowError, match="ask for float32"):
        exr_sequence_zip([np.full((4, 4), 1e-9)], io.BytesIO(), half=True)


@pytest.mark.parametrize(
    "frames",
    [[], [np.ones((4, 4)), np.ones((4, 6))], [np.full((4, 4), np.nan)], [-np.ones((4, 4))],
     [np.ones((4, 4, 2))]],
    ids=["empty", "mixed-shapes", "nan", "negative", "two-channels"],
)
def test_bad_clips_are_refused(frames: list[np.ndarray]) -> None:
    with pytest.raises(InvalidInputError):
        write_hdr10(frames, io.BytesIO())


@pytest.mark.parametrize(
    "settings",
    [
        {"fps": 0}, {"fps": float("inf")}, {"fps": 0.0003}, {"fps": 1e9}, {"fps": float("nan")},
        {"white_level": -1}, {"white_level": float("inf")}, {"white_level": 1e-300},
        {"reference_white": 1e-300}, {"reference_white": 10_001}, {"reference_white": 1e308},
        {"mastering_peak": 20_000}, {"crf": 99}, {"crf": -3}, {"preset": "bogus"},
    ],
)  # fmt: skip
def test_bad_settings_are_refused(settings: dict) -> None:
    with pytest.raises(InvalidInputError, match=f"{next(iter(settings)).split('_')[0]}"):
        Hdr10Settings(**settings)


@pytest.mark.parametrize(
    ("fps", "rate"),
    [(23.976, Fraction(24000, 1001)), (29.97, Fraction(30000, 1001)),
     (59.94, Fraction(60000, 1001)), (24, Fraction(24)), (12.5, Fraction(25, 2)),
     (23.98, Fraction(24000, 1001)), (30, Fraction(30)),
     (0.1, Fraction(1, 10))],
)  # fmt: skip
def test_frame_rates_are_exact_and_ntsc_rates_recognised(fps: float, rate: Fraction) -> None:
    assert frame_rate(fps) == rate


@pytest.mark.parametrize(
    ("fps", "crf"), [(0, 20), (-5, 20), (float("nan"), 20), (1e9, 20), (30, 99)]
)
def test_the_sdr_preview_refuses_rates_and_qualities_it_cannot_encode(
    fps: float, crf: int
) -> None:
    """fps 0 gave a 24 fps file, 1e9 a file of no frames, -5 and NaN bare errors."""
    with pytest.raises(InvalidInputError, match="fps|crf"):
        write_sdr_preview(grey_clip(16, 16), io.BytesIO(), fps=fps, crf=crf)


@pytest.mark.parametrize("bad", [-1e-9, np.inf, np.nan])
def test_the_exr_sequence_refuses_what_the_videos_refuse(bad: float) -> None:
    """A negative pixel was stored, and inf was called an overflow to fix with the gain."""
    frame = np.ones((4, 4))
    frame[1, 2] = bad
    with pytest.raises(InvalidInputError, match="not finite or are negative"):
        exr_sequence_zip([np.ones((4, 4)), frame], io.BytesIO())


def test_light_levels_count_the_pixels_pq_clips() -> None:
    """Past 10000 cd/m^2 (x > 49.3 at the defaults) PQ shows every pixel at its peak;
    only MaxCLL = 10000 said so."""
    levels = light_levels([np.array([[1.0, 49.0], [50.0, 1000.0]])], Hdr10Settings())
    assert levels.max_cll == 10_000 and levels.clipped_share == 0.5
    assert light_levels(grey_clip(), Hdr10Settings(white_level=40.0)).clipped_share == 0.0


def test_hdr10_signals_where_its_chroma_samples_sit() -> None:
    """Chroma averaged over 2 x 2 blocks sits at their centre; unsaid, decoders assume
    the left column (a half-pixel shift at colour edges)."""
    stream_params = x265_params(Hdr10Settings(), light_levels(grey_clip(), Hdr10Settings()), 6)
    assert "chromaloc=1" in stream_params.split(":")


def test_a_frame_past_float64_in_nits_is_the_pq_peak_without_a_warning() -> None:
    frame = np.full((4, 4), 1e308)
    frame[0, 0] = 0.0
    settings = Hdr10Settings(white_level=1.0)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        nits = to_nits(frame, settings)
        luma = hdr10_yuv(frame, settings)[0]
    assert np.isposinf(nits[1:]).all() and (nits[0, 0] == 0.0).all()
    assert luma[1:].min() == luma.max() > luma[0, 0]
