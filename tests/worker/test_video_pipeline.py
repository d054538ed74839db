"""Tests of worker/video_pipeline.py: a wrapped video decoded in chunks, then written."""

from __future__ import annotations

import io
import zipfile
from collections.abc import Iterator
from typing import Any

import numpy as np
import pytest

from models.errors import InvalidInputError, OutputOverflowError
from models.formation import SensorParams, encode
from worker.child_process import ChildProcess
from worker.video_input import WrappedVideo
from worker.video_pipeline import VideoOptions, decode_video_frames, write_outputs

PARAMS = SensorParams(encoding="mantissa", alpha=2.0, bits=8)
FRAMES = 10


def clip() -> WrappedVideo:
    """A smooth blob (up to ~9 wraps) brightening 3% per frame, 32 x 32."""
    yy, xx = np.mgrid[0:32, 0:32] - 16
    base = 0.05 + 8.0 * np.exp(-(yy**2 + xx**2) / 10.0**2)
    return WrappedVideo(
        np.stack([encode(base * 1.03**t, PARAMS).codes for t in range(FRAMES)]), PARAMS
    )


@pytest.fixture(scope="module")
def child() -> Iterator[ChildProcess]:
    process = ChildProcess()
    yield process
    process.close()


def in_child(child: ChildProcess) -> Any:
    """A runner that sends each chunk to ``child``, as a worker's video job does."""
    return lambda function, *args: child.call(function, args, lambda: None)


@pytest.mark.parametrize("mode", ["temporal", "independent"])
def test_chunks_and_the_child_decode_as_one_stream_does(mode: str, child: ChildProcess) -> None:
    video = clip()
    options = VideoOptions(mode=mode, decoder="itoh", keyframes=frozenset({5}))
    whole = decode_video_frames(video, options)
    seen: list[int] = []
    chunked = decode_video_frames(
        video, options, lambda _stage, done, _total: seen.append(done),
        run=in_child(child), chunk=4, chunk_s=1e9,
    )  # fmt: skip
    assert seen == [1, 5, 9, 10]
    np.testing.assert_array_equal(np.stack(chunked.irradiance), np.stack(whole.irradiance))
    reasons = [frame["keyframe"] for frame in chunked.frames]
    assert reasons == [frame["keyframe"] for frame in whole.frames]
    if mode == "temporal":
        assert reasons[0] == "first" and reasons[5] == "discont" and reasons.count(None) == 8
    assert chunked.summary()["frames"] == FRAMES


def test_slow_frames_go_one_at_a_time() -> None:
    """Frames slower than the chunk's time target: one per call, progress every frame."""
    seen: list[int] = []
    decode_video_frames(
        clip(), VideoOptions(decoder="itoh"), lambda _stage, done, _total: seen.append(done),
        chunk=4, chunk_s=0.0,
    )  # fmt: skip
    assert seen == list(range(1, FRAMES + 1))


def test_a_frame_that_cannot_be_decoded_is_named(child: ChildProcess) -> None:
    """Frame 2 of a mantissa clip (alpha 1e6) unwraps past float64: the job failed with
    "192 pixels of the reconstruction exceed ...", naming no frame of its video."""
    params = SensorParams(encoding="mantissa", alpha=1e6, bits=16)
    u = np.tile(np.linspace(0.5, 56.0, 256), (64, 1))
    ramp = np.floor((u % 1) * 65536).astype(np.uint16)
    dark = np.full_like(ramp, 5)
    video = WrappedVideo(np.stack([dark, dark, ramp, dark]), params)
    with pytest.raises(OutputOverflowError, match=r"^video frame 2: \d+ pixels of the recon"):
        decode_video_frames(
            video, VideoOptions(mode="independent", decoder="itoh"), run=in_child(child), chunk=4
        )


def test_unknown_outputs_are_refused() -> None:
    video = clip()
    decoded = decode_video_frames(video, VideoOptions(decoder="itoh"))
    with pytest.raises(InvalidInputError, match="unknown video outputs"):
        write_outputs(decoded, video, {"gif": io.BytesIO()}, VideoOptions())


def test_an_exr_sequence_that_cannot_be_stored_fails_before_any_video_is_encoded() -> None:
    """Half floats cannot hold x / gain past 65504: the job fails at once, naming the
    remedy, rather than after encoding the HDR10 and SDR videos it would then throw away."""
    small = clip()
    codes = small.codes.repeat(2, axis=1).repeat(2, axis=2)  # 64 x 64, HDR10's smallest
    video = WrappedVideo(codes, PARAMS.model_copy(update={"gain": 1e-5}))
    decoded = decode_video_frames(video, VideoOptions(decoder="itoh"))
    stages: list[str] = []
    hdr10, exrs = io.BytesIO(), io.BytesIO()
    with pytest.raises(OutputOverflowError, match="video frame 0"):
        write_outputs(
            decoded, video, {"hdr10": hdr10, "sdr": io.BytesIO(), "exr_zip": exrs},
            VideoOptions(decoder="itoh", half=True),
            lambda stage, _done, _total: stages.append(stage),
        )  # fmt: skip
    assert stages == [] and hdr10.getvalue() == b"" and exrs.getvalue() == b""
    write_outputs(decoded, video, {"exr_zip": exrs}, VideoOptions(decoder="itoh"))
    with zipfile.ZipFile(exrs) as archive:
        assert len(archive.namelist()) == FRAMES


def test_the_exr_sequence_reports_progress_after_each_frame() -> None:
    """The EXR sequence reported once, when its zip was whole: a video job's progress
    stood still and its cancel went unread through that stage (9 s for 2^26 samples)."""
    video = clip()
    decoded = decode_video_frames(video, VideoOptions(decoder="itoh"))
    reports: list[tuple[str, int, int]] = []
    write_outputs(
        decoded, video, {"exr_zip": io.BytesIO()}, VideoOptions(decoder="itoh"),
        lambda stage, done, total: reports.append((stage, done, total)),
    )  # fmt: skip
    assert reports == [("exr_zip", done, FRAMES) for done in range(1, FRAMES + 1)]
