"""Tests of ``mcam evaluate`` through the real console script."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from models.hdr_io import read_hdr, write_exr
from models.metrics import evaluate
from tests.service.cli.conftest import assert_one_line_error, run_mcam


def test_evaluate_json_matches_the_metrics_module(pipeline: Path) -> None:
    result = run_mcam(
        "evaluate", "hdr.exr", "--reference", "reference.exr", "--winding", "W.png",
        "--winding-reference", "W_true.png", "--json", "--no-flip",
        cwd=pipeline,
    )  # fmt: skip
    assert result.returncode == 0, result.stderr
    printed = json.loads(result.stdout)
    expected = evaluate(
        read_hdr(pipeline / "hdr.exr").pixels,
        read_hdr(pipeline / "reference.exr").pixels,
        flip=False,
    )
    assert printed["winding_accuracy"] == 1.0
    for name, value in expected.items():
        assert printed[name] == value
    assert printed["psnr"] > 40.0


def test_evaluate_table_and_identical_images(pipeline: Path) -> None:
    table = run_mcam("evaluate", "hdr.exr", "--reference", "reference.exr", cwd=pipeline)
    assert table.returncode == 0, table.stderr
    lines = table.stdout.splitlines()
    assert lines[0].startswith("PSNR (linear)")
    assert lines[0].endswith("dB")
    assert any(line.startswith("PU21-PSNR") for line in lines)
    same = run_mcam(
        "evaluate", "reference.exr", "--reference", "reference.exr", "--json", "--no-flip",
        cwd=pipeline,
    )  # fmt: skip
    assert json.loads(same.stdout)["psnr"] is None


def test_evaluate_bad_input(tmp_path: Path, pipeline: Path) -> None:
    write_exr(tmp_path / "small.exr", np.ones((5, 5)))
    assert_one_line_error(
        run_mcam("evaluate", pipeline / "hdr.exr", "--reference", "small.exr", cwd=tmp_path),
        "shape",
    )
    assert_one_line_error(
        run_mcam(
            "evaluate",
            pipeline / "hdr.exr",
            "--reference",
            pipeline / "reference.exr",
            "--winding",
            pipeline / "W.png",
            cwd=tmp_path,
        ),  # fmt: skip
        "winding",
    )


def test_one_winding_map_without_the_other_names_the_flag_to_add(pipeline: Path) -> None:
    """It was "winding accuracy needs both the estimated and the reference winding
    maps", naming neither flag, after both images had been read."""
    images = ("evaluate", "hdr.exr", "--reference", "reference.exr", "--no-flip")
    alone = run_mcam(*images, "--winding", "W.png", cwd=pipeline)
    assert_one_line_error(alone, "--winding needs --winding-reference (the true W map, as mcam")
    alone = run_mcam(*images, "--winding-reference", "W_true.png", cwd=pipeline)
    assert_one_line_error(alone, "--winding-reference needs --winding (the decoded W map")


def test_evaluate_clips_negative_values_when_asked(tmp_path: Path, pipeline: Path) -> None:
    lossy = np.ones((8, 8))
    lossy[0, 0] = -0.5  # a lossy codec's undershoot
    write_exr(tmp_path / "lossy.exr", lossy)
    refused = run_mcam("evaluate", "lossy.exr", "--reference", "lossy.exr", cwd=tmp_path)
    assert_one_line_error(refused, "negative", "--clip-negative")
    clipped = run_mcam(
        "evaluate", "lossy.exr", "--reference", "lossy.exr", "--clip-negative", "--no-flip",
        "--json", cwd=tmp_path,
    )  # fmt: skip
    assert clipped.returncode == 0, clipped.stderr
    assert json.loads(clipped.stdout)["psnr"] is None  # identical after clipping: infinite


def test_evaluate_measures_hdr_flip_on_tiny_values(tmp_path: Path) -> None:
    """FLIP's own exposure range collapses below ~1e-7 and it used to end the process."""
    write_exr(tmp_path / "tiny.exr", 1e-8 * np.linspace(0.5, 2.0, 256).reshape(16, 16))
    write_exr(tmp_path / "flat.exr", np.full((16, 16), 1e-30))
    for name in ("tiny.exr", "flat.exr"):
        result = run_mcam("evaluate", name, "--reference", name, "--json", cwd=tmp_path)
        assert result.returncode == 0, result.stderr
        assert json.loads(result.stdout)["hdr_flip"] == 0.0


def test_images_too_small_for_ssim_say_why_it_is_missing(tmp_path: Path) -> None:
    write_exr(tmp_path / "small.exr", np.linspace(0.5, 2.0, 40).reshape(4, 10))
    write_exr(tmp_path / "large.exr", np.linspace(0.5, 2.0, 121).reshape(11, 11))
    small = run_mcam("evaluate", "small.exr", "--reference", "small.exr", "--json", cwd=tmp_path)
    assert small.returncode == 0 and "ssim" not in json.loads(small.stdout)
    assert small.stderr.strip() == (
        "mcam evaluate: note: no SSIM or MS-SSIM: they need images of at least 11 x 11 "
        "pixels (their window), these are 4 x 10"
    )
    large = run_mcam("evaluate", "large.exr", "--reference", "large.exr", "--json", cwd=tmp_path)
    assert large.returncode == 0 and "ssim" in json.loads(large.stdout)
    assert large.stderr == ""


def test_a_reconstruction_in_wrap_units_is_not_compared_with_a_scene_referred_one(
    tmp_path: Path, pipeline: Path
) -> None:
    """A frame reconstructed without its gain is in wrap units (x, not x / gain): its PSNR
    against the scene-referred reference compared two scales without a word."""
    reference = read_hdr(pipeline / "reference.exr")
    wrap_units = {"comments": "MantissaCam reconstruction of f.npy; values in wrap units x "
                              "(gain unknown)"}
    write_exr(tmp_path / "hdr.exr", reference.pixels * 7.0, wrap_units)
    gain = reference.attributes["gain"]
    assert_one_line_error(
        run_mcam("evaluate", tmp_path / "hdr.exr", "--reference", pipeline / "reference.exr",
                 cwd=tmp_path),
        "mcam evaluate: error:", "in wrap units (its gain was unknown)",
        "reference is in scene-referred x / gain", f"--gain {gain}",
    )  # fmt: skip


def test_a_bad_winding_map_is_named_among_the_two(tmp_path: Path, pipeline: Path) -> None:
    """With --winding and --winding-reference both given, an empty or float map was refused
    as 'the PNG winding map is truncated' or 'a winding map holds integers' without
    saying which of the two files it was."""
    np.save(tmp_path / "float.npy", np.zeros((64, 64), np.float32))
    images = (pipeline / "hdr.exr", "--reference", pipeline / "reference.exr", "--no-flip")
    result = run_mcam("evaluate", *images, "--winding", pipeline / "W.png",
                      "--winding-reference", "float.npy", cwd=tmp_path)  # fmt: skip
    assert_one_line_error(result, "error: float.npy: ", "integers")


def test_an_empty_file_is_called_empty(tmp_path: Path, pipeline: Path) -> None:
    """An empty image was called "not an OpenEXR or Radiance HDR image; convert it to
    OpenEXR" (an empty W map "truncated or corrupt"), where mcam video, reconstruct and
    simulate say the file is empty (:func:`models.file_magic.refuse_empty`)."""
    (tmp_path / "e.exr").write_bytes(b"")
    (tmp_path / "empty.png").write_bytes(b"")
    images = (pipeline / "hdr.exr", "--reference", pipeline / "reference.exr", "--no-flip")
    maps = ("--winding", pipeline / "W.png", "--winding-reference", "empty.png")
    for empty, args in (
        ("e.exr", ("e.exr", "--reference", "e.exr")),
        ("e.exr", (pipeline / "hdr.exr", "--reference", "e.exr")),
        ("empty.png", (*images, *maps)),
    ):
        assert_one_line_error(
            run_mcam("evaluate", *args, cwd=tmp_path),
            f"error: the file {empty} is empty; send the whole file",
        )


def test_a_wrapped_frame_given_as_a_winding_map_is_refused(tmp_path: Path, pipeline: Path) -> None:
    """The frame (wrapped.png) given for the true W map (W_true.png), a name away, had
    its codes read as winding numbers: a winding accuracy of 0.03, without a word."""
    result = run_mcam(
        "evaluate", pipeline / "hdr.exr", "--reference", pipeline / "reference.exr",
        "--no-flip", "--winding", pipeline / "W.png",
        "--winding-reference", pipeline / "wrapped.png", cwd=tmp_path,
    )  # fmt: skip
    assert_one_line_error(result, "wrapped.png: this is a wrapped frame", "not a winding map")
