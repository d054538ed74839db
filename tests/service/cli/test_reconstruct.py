"""Tests of ``mcam reconstruct`` through the real console script."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import OpenEXR

from models.formation import SensorParams, encode, simulate
from models.frames import write_frame
from models.hdr_io import read_hdr
from models.winding_files import read_winding
from service.cli.reconstruct import decoder_notes
from tests.service.cli.conftest import (
    assert_one_line_error,
    blob_scene,
    mantissa_tolerance,
    run_mcam,
)


def test_itoh_recovers_the_smooth_scene(pipeline: Path) -> None:
    """Every W right, and x_hat within the 8-bit mantissa bound of the reference."""
    np.testing.assert_array_equal(
        read_winding(pipeline / "W.png"), read_winding(pipeline / "W_true.png")
    )
    image = read_hdr(pipeline / "hdr.exr")
    reference = read_hdr(pipeline / "reference.exr").pixels
    assert image.pixels.shape == reference.shape
    tolerance = mantissa_tolerance(reference, float(image.attributes["gain"]), bits=8, alpha=2.0)
    assert np.all(np.abs(image.pixels - reference) <= tolerance)


def test_exr_attributes_record_the_decode(pipeline: Path) -> None:
    attributes = read_hdr(pipeline / "hdr.exr").attributes
    assert attributes["encoding"] == "mantissa"
    assert attributes["alpha"] == "2.0"
    assert attributes["bits"] == "8"
    assert attributes["decoder"] == "itoh"
    assert attributes["decoderVersion"]
    assert "scene-referred" in attributes["comments"]
    assert "capDate" in attributes
    assert "decoder itoh" in (pipeline / "reconstruct.out").read_text()


def test_flags_fill_in_a_bare_npy_and_half_output(tmp_path: Path) -> None:
    """An npy frame has no stored params: the flags supply them; without gain, x is written."""
    params = SensorParams(encoding="modulo", bits=10, gain=1.0)
    frame = simulate(blob_scene(size=48, peak=6.0, halving=10.0), params)
    np_path = tmp_path / "bare.npy"
    write_frame(np_path, frame.codes, None)
    result = run_mcam(
        "reconstruct", np_path, "-o", "x.exr", "--encoding", "modulo", "--bits", "10", "--half",
        "--decoder", "herraez", "--exr-compression", "none",
        cwd=tmp_path,
    )  # fmt: skip
    assert result.returncode == 0, result.stderr
    header = OpenEXR.File(str(tmp_path / "x.exr"), header_only=True).header()
    assert header["compression"] == OpenEXR.NO_COMPRESSION
    image = read_hdr(tmp_path / "x.exr")
    assert "gain" not in image.attributes
    assert "wrap units" in image.attributes["comments"]
    # 10-bit bin centre, then half-float rounding (11 significant bits)
    assert np.all(np.abs(image.pixels - frame.irradiance) <= 2.0**-11 * (1.0 + frame.irradiance))


def test_list_decoders(tmp_path: Path) -> None:
    result = run_mcam("reconstruct", "--list-decoders", cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    names = [line.split()[0] for line in result.stdout.splitlines()]
    assert {"itoh", "herraez"} <= set(names)
    assert "least-squares" in result.stdout
    assert "also: auto-<N>ms" in result.stdout


def test_reconstruct_within_a_latency_budget(tmp_path: Path, pipeline: Path) -> None:
    out = tmp_path / "budget.exr"
    result = run_mcam("reconstruct", str(pipeline / "wrapped.png"), "-o", str(out),
                      "--decoder", "auto-5000ms",
                      cwd=tmp_path)  # fmt: skip
    assert result.returncode == 0, result.stderr
    assert out.exists()
    summary = result.stdout.splitlines()[-1]
    assert summary.startswith("latency budget 5000 ms: ") and "within budget" in summary
    assert "(once per process)" in summary


def write_colour_npy(folder: Path) -> None:
    """A 48 x 48 colour modulo frame (8 bits) as ``colour.npy`` in ``folder``."""
    params = SensorParams(encoding="modulo", bits=8, gain=1.0)
    scene = blob_scene(size=48, peak=6.0, halving=10.0)
    frame = simulate(np.stack([scene, 0.7 * scene, 0.4 * scene], axis=2), params)
    write_frame(folder / "colour.npy", frame.codes, None)


def test_a_colour_frame_shares_its_latency_budget(tmp_path: Path) -> None:
    write_colour_npy(tmp_path)
    result = run_mcam("reconstruct", "colour.npy", "-o", "x.exr", "--encoding", "modulo",
                      "--bits", "8", "--decoder", "auto-5000ms", cwd=tmp_path)  # fmt: skip
    assert result.returncode == 0, result.stderr
    lines = result.stdout.splitlines()
    assert sum(line.startswith("latency budget ") for line in lines) == 4
    assert lines[-1].startswith("latency budget 5000 ms for the colour frame, shared by")
    assert "(made consistent)" in lines[-1] and "within budget; measuring" in lines[-1]
    assert lines[-1].endswith("(once per process)")
    routing = json.loads(read_hdr(tmp_path / "x.exr").attributes["routing"])
    assert routing["budget"]["joined"] is True and len(routing["channels"]) == 3


def test_reconstruct_bad_input(tmp_path: Path, pipeline: Path) -> None:
    np.save(tmp_path / "bare.npy", np.zeros((8, 8), np.uint8))
    np.save(tmp_path / "float.npy", np.zeros((8, 8), np.float32))
    missing = run_mcam("reconstruct", "bare.npy", "-o", "x.exr", cwd=tmp_path)
    assert_one_line_error(missing, "--encoding", "--bits")
    assert_one_line_error(
        run_mcam("reconstruct", "nope.png", "-o", "x.exr", cwd=tmp_path), "no such file", "nope.png"
    )
    floats = run_mcam(
        "reconstruct", "float.npy", "-o", "x.exr", "--encoding", "modulo", "--bits", "8",
        cwd=tmp_path,
    )  # fmt: skip
    assert_one_line_error(floats, "integers", "float32")
    assert_one_line_error(
        run_mcam(
            "reconstruct",
            pipeline / "wrapped.png",
            "-o",
            "x.exr",
            "--decoder",
            "magic",
            cwd=tmp_path,
        ),  # fmt: skip
        "unknown decoder",
        "itoh",
    )
    overflow = run_mcam(
        "reconstruct", pipeline / "wrapped.png", "-o", "x.exr", "--gain", "1e-6", "--half",
        cwd=tmp_path,
    )  # fmt: skip
    assert_one_line_error(overflow, "float16")
    underflow = run_mcam(
        "reconstruct", pipeline / "wrapped.png", "-o", "x.exr", "--gain", "1e308",
        cwd=tmp_path,
    )  # fmt: skip
    assert_one_line_error(underflow, "would be stored as 0", "lower the gain")
    assert not (tmp_path / "x.exr").exists()
    not_exr = run_mcam(
        "reconstruct", pipeline / "wrapped.png", "-o", "x.txt", cwd=tmp_path
    )  # fmt: skip
    assert_one_line_error(not_exr, "x.txt", "name the file .exr")
    assert not (tmp_path / "x.txt").exists()


def test_reconstruct_checks_its_outputs_before_decoding(tmp_path: Path, pipeline: Path) -> None:
    frame = pipeline / "wrapped.png"
    winding_exr = run_mcam("reconstruct", frame, "-o", "x.exr", "--winding-out", "W.exr",
                           cwd=tmp_path)  # fmt: skip
    assert_one_line_error(winding_exr, "--winding-out W.exr: a W map", ".png")
    folder = run_mcam("reconstruct", frame, "-o", "adir.exr/", cwd=tmp_path)
    assert_one_line_error(folder, "-o adir.exr/ names a folder")
    assert list(tmp_path.iterdir()) == []


def test_a_gain_no_winding_numbers_can_store_is_refused_before_decoding(
    tmp_path: Path, pipeline: Path
) -> None:
    """x / gain at gain 1e-320 exceeds float32 at W = 0 already: it was found after the
    decode."""
    result = run_mcam("reconstruct", pipeline / "wrapped.png", "-o", "x.exr", "--gain",
                      "1e-320", cwd=tmp_path)  # fmt: skip
    assert_one_line_error(result, "whatever winding numbers a decoder finds", "higher gain")
    assert list(tmp_path.iterdir()) == []


def test_a_colour_frames_w_map_as_png_is_refused_before_decoding(tmp_path: Path) -> None:
    """It was refused after the decode (seconds at best), and the EXR not written."""
    write_colour_npy(tmp_path)
    result = run_mcam("reconstruct", "colour.npy", "-o", "x.exr", "--encoding", "modulo",
                      "--bits", "8", "--decoder", "itoh", "--winding-out", "W.png",
                      cwd=tmp_path)  # fmt: skip
    assert_one_line_error(result, "colour.npy is a colour frame", ".tiff or .npy")
    assert "decoder" not in result.stdout  # nothing decoded, nothing written


def test_a_png_named_tiff_is_decoded_as_the_png_it_is(tmp_path: Path, pipeline: Path) -> None:
    """It was 'the TIFF frame is truncated or corrupt (not a TIFF file: header=b'\\x89PNG')'."""
    (tmp_path / "wrapped.tiff").write_bytes((pipeline / "wrapped.png").read_bytes())
    result = run_mcam("reconstruct", "wrapped.tiff", "-o", "x.exr", cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    assert "content is PNG although its name or declared format says TIFF" in result.stderr
    np.testing.assert_array_equal(
        read_hdr(tmp_path / "x.exr").pixels, read_hdr(pipeline / "hdr.exr").pixels
    )


def test_8_bit_codes_read_as_16_bit_are_warned_about_on_stderr(tmp_path: Path) -> None:
    """The warning the API now returns in a job's ``warnings`` is still printed here."""
    write_frame(tmp_path / "f.npy", np.arange(64, dtype=np.uint8).reshape(8, 8), None)
    result = run_mcam("reconstruct", "f.npy", "-o", "x.exr", "--encoding", "modulo",
                      "--bits", "16", cwd=tmp_path)  # fmt: skip
    assert result.returncode == 0, result.stderr
    assert "every code is below 256 although bits is 16" in result.stderr
    assert "--bits 8" in result.stderr


def test_a_clip_frame_one_pixel_high_is_decoded(tmp_path: Path) -> None:
    """A clipped sensor never wraps, so a 1 x N frame needs no neighbours: it was refused
    as having none to unwrap against ("spatial decoders need at least 2 x 2 pixels")."""
    codes = np.arange(40, dtype=np.uint8)[None, :]
    write_frame(tmp_path / "row.png", codes, SensorParams(encoding="clip", gain=2.0))
    result = run_mcam("reconstruct", "row.png", "-o", "x.exr", "--decoder", "auto",
                      "--winding-out", "W.png", cwd=tmp_path)  # fmt: skip
    assert result.returncode == 0, result.stderr
    np.testing.assert_allclose(read_hdr(tmp_path / "x.exr").pixels, (codes + 0.5) / 256 / 2.0)
    assert not read_winding(tmp_path / "W.png").any()


def log_ramp_frame(folder: Path, high: float) -> None:
    """``ramp.png``: a 96 x 96 mantissa frame of a diagonal log ramp from 0.01 to ``high``
    (x, gain 1), W up to ``1 + log2(high)``, but for a dark band on its left with a step
    up by 0.65 wrap in its upper quarter and 0.35 below, which leaves residues (a frame
    without any is integrated, the net not run)."""
    rows, cols = np.mgrid[0:96, 0:96]
    params = SensorParams(encoding="mantissa", alpha=2.0, bits=8, gain=1.0)
    x = 1e-2 * (high / 1e-2) ** ((rows + cols) / 190)
    x[:, :8] = 0.1
    x[:24, 2:6] = 0.75
    x[24:, 2:6] = 0.45
    frame = encode(x, params)
    write_frame(folder / "ramp.png", frame.codes, params)


def test_a_nets_fallback_and_warning_are_printed(tmp_path: Path) -> None:
    """A net hands a frame mostly beyond its classes to herraez, and warns of one a little
    beyond them: the API's job showed it in its details, mcam reconstruct said nothing
    (nor for a net guiding +puma) and named the net as the decoder."""
    log_ramp_frame(tmp_path, 1e30)
    for decoder in ("mantissanet-small", "mantissanet-small+puma"):
        result = run_mcam("reconstruct", "ramp.png", "-o", "x.exr", "--decoder", decoder,
                          cwd=tmp_path)  # fmt: skip
        assert result.returncode == 0, result.stderr
        (note,) = result.stderr.splitlines()
        assert note.startswith("mcam reconstruct: note: ")
        assert note.endswith("herraez decoded it; for such frames choose itoh, herraez or auto")
    log_ramp_frame(tmp_path, 3e5)
    result = run_mcam("reconstruct", "ramp.png", "-o", "x.exr", "--decoder", "unmodnet",
                      cwd=tmp_path)  # fmt: skip
    assert result.returncode == 0, result.stderr
    (warning,) = result.stderr.splitlines()
    assert warning.startswith("mcam reconstruct: warning: ")
    assert "the net's W is short there" in warning


def test_decoder_notes_are_found_anywhere_once() -> None:
    warning = {"warning": "short"}
    info = {
        "decoder": "x",
        "channels": [warning, warning, {"guide_details": {"fallback": {"reason": "handed"}}}],
    }
    assert decoder_notes(info) == [("warning", "short"), ("note", "handed")]
    assert decoder_notes({"decoder": "itoh", "details": {"routes": {"integration": 1.0}}}) == []


def test_a_grey_frame_stored_h_x_w_x_1_writes_a_png_w_map(tmp_path: Path) -> None:
    """It was refused as "a colour frame: its W map has 3 channels, which a PNG W map
    cannot hold", and the PNG W map of an H x W x 1 W (its decode) was refused too."""
    codes = np.arange(64, dtype=np.uint8).reshape(8, 8, 1)
    write_frame(tmp_path / "grey.npy", codes, None)
    result = run_mcam("reconstruct", "grey.npy", "-o", "x.exr", "--encoding", "modulo",
                      "--bits", "8", "--winding-out", "W.png", cwd=tmp_path)  # fmt: skip
    assert result.returncode == 0, result.stderr
    np.testing.assert_array_equal(read_winding(tmp_path / "W.png"), np.zeros((8, 8)))
