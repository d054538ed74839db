"""Tests of ``mcam video`` through the real console script."""

from __future__ import annotations

import io
import json
import zipfile
from pathlib import Path

import av
import numpy as np
import OpenEXR

from models.formation import SensorParams, encode
from models.hdr_io import read_hdr
from tests.service.cli.conftest import assert_one_line_error, mantissa_tolerance, run_mcam

FLAGS = ("--encoding", "mantissa", "--alpha", "2", "--bits", "8")
FRAMES, SIZE = 8, 64


def slow_clip() -> list[np.ndarray]:
    """A smooth blob (x up to ~9) brightening 3% per frame: exact for itoh and temporally."""
    yy, xx = np.mgrid[0:SIZE, 0:SIZE] - SIZE / 2
    base = 0.05 + 8.0 * np.exp(-(yy**2 + xx**2) / 20.0**2)
    return [base * 1.03**t for t in range(FRAMES)]


def test_video_writes_hdr10_preview_and_exr_frames(tmp_path: Path) -> None:
    params = SensorParams(encoding="mantissa", alpha=2.0, bits=8)
    truth = slow_clip()
    np.save(tmp_path / "wrapped.npy", np.stack([encode(x, params).codes for x in truth]))
    result = run_mcam(
        "video", "wrapped.npy", "-o", "clip.mp4", "--mode", "temporal", *FLAGS,
        "--preview", "sdr.mp4", "--exr", "frames.zip", "--exr-compression", "none",
        cwd=tmp_path,
    )  # fmt: skip
    assert result.returncode == 0, result.stderr
    # stderr is no terminal here: one finished line per stage, no carriage-return redraws
    assert result.stderr.splitlines() == [
        f"{stage:<8} [{'#' * 30}] {FRAMES}/{FRAMES} frames"
        for stage in ("decode", "hdr10", "sdr", "exr_zip")
    ]
    assert f"{FRAMES} frames, mode temporal" in result.stdout
    with av.open(str(tmp_path / "clip.mp4")) as container:
        stream = container.streams.video[0]
        assert stream.codec_context.name == "hevc"
        assert sum(1 for _ in container.decode(stream)) == FRAMES
    with av.open(str(tmp_path / "sdr.mp4")) as container:
        assert container.streams.video[0].codec_context.name == "h264"
    with zipfile.ZipFile(tmp_path / "frames.zip") as archive:
        names = archive.namelist()
        assert len(names) == FRAMES
        for name, x in zip(names, truth, strict=True):
            data = archive.read(name)
            header = OpenEXR.File(io.BytesIO(data), header_only=True).header()
            assert header["compression"] == OpenEXR.NO_COMPRESSION
            # the provenance mcam reconstruct writes, and the stream's facts
            assert (header["encoding"], header["alpha"], header["bits"]) == ("mantissa", "2.0", "8")
            assert (header["decoder"], header["decoderVersion"]) == ("itoh", "1")
            assert header["comments"].endswith("values in wrap units x (gain unknown)")
            assert json.loads(header["temporal"])["mode"] == "temporal"
            pixels = read_hdr(data).pixels
            bound = mantissa_tolerance(x, 1.0, bits=8, alpha=2.0)
            assert np.all(np.abs(pixels - x) <= bound)


def test_video_refuses_an_unknown_output(tmp_path: Path) -> None:
    np.save(tmp_path / "wrapped.npy", np.zeros((2, 8, 8), np.uint8))
    result = run_mcam("video", "wrapped.npy", "-o", "clip.avi", *FLAGS, cwd=tmp_path)
    assert_one_line_error(result, "clip.avi", ".mp4")


def test_video_needs_parameters(tmp_path: Path) -> None:
    np.save(tmp_path / "wrapped.npy", np.zeros((2, 8, 8), np.uint8))
    result = run_mcam("video", "wrapped.npy", "-o", "frames.zip", cwd=tmp_path)
    assert_one_line_error(result, "--encoding")


def test_frames_too_small_for_hdr10_are_refused_before_decoding(tmp_path: Path) -> None:
    np.save(tmp_path / "wrapped.npy", np.zeros((3, 32, 32), np.uint8))
    result = run_mcam("video", "wrapped.npy", "-o", "clip.mp4", *FLAGS, cwd=tmp_path)
    assert_one_line_error(result, "64 x 64", "got 32 x 32", "-o clip.zip")


def test_frames_too_wide_for_the_sdr_preview_are_refused_before_decoding(
    tmp_path: Path,
) -> None:
    """libx264 takes sides up to 16384: wider frames were decoded, then the preview
    failed with "Generic error in an external library"."""
    np.save(tmp_path / "wrapped.npy", np.zeros((2, 2, 16386), np.uint8))
    result = run_mcam(
        "video", "wrapped.npy", "-o", "f.zip", "--preview", "p.mp4", *FLAGS, cwd=tmp_path
    )
    assert_one_line_error(result, "at most 16384 pixels a side, got 2 x 16386", "drop --preview")
    assert sorted(path.name for path in tmp_path.iterdir()) == ["wrapped.npy"]


def test_video_refuses_clashing_or_misnamed_outputs_before_decoding(tmp_path: Path) -> None:
    np.save(tmp_path / "wrapped.npy", np.zeros((2, 64, 64), np.uint8))
    cases = [
        (("-o", "a.zip", "--exr", "b.zip"), "-o a.zip already writes the EXR frames"),
        (("-o", "s.mp4", "--preview", "s.mp4"), "-o and --preview both name s.mp4"),
        (("-o", "s.mp4", "--preview", "p.zip"), "--preview p.zip", ".mp4"),
        (("-o", "s.mp4", "--exr", "e.mp4"), "--exr e.mp4", ".zip"),
        (("-o", "clip.mov",), "-o clip.mov", ".mp4"),
        (("-o", "nofolder/x.mp4",), "no such folder: nofolder"),
    ]
    for outputs, *fragments in cases:
        result = run_mcam("video", "wrapped.npy", *outputs, *FLAGS, cwd=tmp_path)
        assert_one_line_error(result, *fragments)
    assert [path.name for path in tmp_path.iterdir()] == ["wrapped.npy"]


def test_a_failing_output_leaves_no_other_output_behind(tmp_path: Path) -> None:
    params = SensorParams(encoding="mantissa", alpha=2.0, bits=8)
    np.save(tmp_path / "wrapped.npy", np.stack([encode(x, params).codes for x in slow_clip()]))
    result = run_mcam(
        "video", "wrapped.npy", "-o", "clip.mp4", "--preview", "sdr.mp4", "--exr", "frames.zip",
        *FLAGS, "--gain", "1e300", "--quiet", cwd=tmp_path,
    )  # fmt: skip
    assert_one_line_error(result, "would be stored as 0")  # the EXR frames
    assert [path.name for path in tmp_path.iterdir()] == ["wrapped.npy"]


def test_exr_frames_that_cannot_be_stored_are_refused_before_decoding(tmp_path: Path) -> None:
    """At gain 1e-300 every x / gain overflows half floats (and float32): the video was
    decoded frame by frame (its progress line written) before the EXR frames were refused.
    ``POST /v1/videos`` refuses such a clip before queuing it; so does ``mcam video``."""
    params = SensorParams(encoding="mantissa", alpha=2.0, bits=8)
    np.save(tmp_path / "wrapped.npy", np.stack([encode(x, params).codes for x in slow_clip()]))
    result = run_mcam(
        "video", "wrapped.npy", "-o", "clip.mp4", "--exr", "frames.zip", "--half", *FLAGS,
        "--gain", "1e-300", cwd=tmp_path,
    )  # fmt: skip
    assert_one_line_error(result, "video frame 0", "float16", "float32 output cannot hold")
    assert [path.name for path in tmp_path.iterdir()] == ["wrapped.npy"]


def test_exr_frames_stored_as_zero_are_refused_at_the_first_such_frame(tmp_path: Path) -> None:
    """An all-dark clip at gain 1e6 in half floats is stored as 0 from frame 0 on (a
    W > 0 would keep it, so it is not refused before decoding): every frame was decoded
    (its progress line written) before frame 0 was refused."""
    np.save(tmp_path / "wrapped.npy", np.zeros((FRAMES, SIZE, SIZE), np.uint8))
    result = run_mcam(
        "video", "wrapped.npy", "-o", "frames.zip", "--half", *FLAGS, "--gain", "1e6",
        cwd=tmp_path,
    )  # fmt: skip
    assert_one_line_error(result, "of the video frame 0 are below the smallest float16")


def test_video_refuses_settings_that_render_no_picture(tmp_path: Path) -> None:
    np.save(tmp_path / "wrapped.npy", np.zeros((2, 64, 64), np.uint8))
    cases = [
        (("--fps", "inf"), "fps must be from 0.1 to 1000"),
        (("--fps", "0.0003"), "fps must be from 0.1 to 1000"),
        (("--white-level", "1e-300"), "white_level must be from"),
        (("--reference-white", "10001"), "reference_white must be from 1 to 10000 cd/m^2"),
    ]
    for flags, fragment in cases:
        result = run_mcam("video", "wrapped.npy", "-o", "c.mp4", *FLAGS, *flags, cwd=tmp_path)
        assert_one_line_error(result, fragment)


def test_odd_sized_frames_are_said_to_be_padded(tmp_path: Path) -> None:
    np.save(tmp_path / "wrapped.npy", np.zeros((2, 65, 67), np.uint8))
    result = run_mcam("video", "wrapped.npy", "-o", "c.mp4", *FLAGS, "--quiet", cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    assert "the MP4 videos are 66 x 68" in result.stdout
    assert "65 x 67 frames is repeated" in result.stdout


def test_a_decoder_without_a_model_for_the_encoding_is_refused_before_decoding(
    tmp_path: Path,
) -> None:
    """mantissanet-tiny-noise has a mantissa model only. On a modulo clip the command
    failed with "video frame 0: decoder ... has no model for the 'modulo' encoding", as
    if frame 0 were bad, naming no decoder that has one."""
    params = SensorParams(encoding="modulo", bits=8)
    clip = slow_clip()[:2]
    np.save(tmp_path / "wrapped.npy", np.stack([encode(x, params).codes for x in clip]))
    result = run_mcam(
        "video", "wrapped.npy", "-o", "f.zip", "--encoding", "modulo", "--bits", "8",
        "--mode", "independent", "--decoder", "mantissanet-tiny-noise", cwd=tmp_path,
    )  # fmt: skip
    assert_one_line_error(
        result, "decoder 'mantissanet-tiny-noise' has no model for modulo frames",
        "choose one that does: itoh, herraez", "mantissanet-tiny,",
    )  # fmt: skip
    assert "video frame" not in result.stderr
    assert "mantissanet-tiny-noise," not in result.stderr
    assert sorted(path.name for path in tmp_path.iterdir()) == ["wrapped.npy"]
