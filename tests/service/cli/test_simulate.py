"""Tests of ``mcam simulate`` through the real console script."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from models.formation import reconstruct
from models.frames import read_frame
from models.hdr_io import read_hdr, write_exr
from models.winding_files import read_winding
from tests.service.cli.conftest import (
    assert_one_line_error,
    blob_scene,
    mantissa_tolerance,
    run_mcam,
)


def test_simulate_writes_frame_ground_truth_and_reference(pipeline: Path) -> None:
    frame = read_frame(pipeline / "wrapped.png")
    assert frame.codes.shape == (64, 64)
    assert frame.codes.dtype == np.uint8
    assert (frame.params.encoding, frame.params.alpha, frame.params.bits) == ("mantissa", 2.0, 8)
    scene = read_hdr(pipeline / "scene.exr").pixels
    # --overexposed 0.2: a fifth of the pixels reach x >= 1.
    assert abs(np.mean(scene * frame.params.gain >= 1.0) - 0.2) <= 2.0 / scene.size
    winding = read_winding(pipeline / "W_true.png")
    assert winding.min() == 0
    assert winding.max() >= 5
    reference = read_hdr(pipeline / "reference.exr")
    np.testing.assert_allclose(reference.pixels, scene, rtol=1e-6)
    assert reference.attributes["encoding"] == "mantissa"
    assert float(reference.attributes["gain"]) == frame.params.gain
    assert "wrote wrapped.png" in (pipeline / "simulate.out").read_text()


def test_true_winding_inverts_the_frame(pipeline: Path) -> None:
    """Codes + the true W give the reference back within half a quantization bin."""
    frame = read_frame(pipeline / "wrapped.png")
    winding = read_winding(pipeline / "W_true.png")
    x_hat = reconstruct(frame.codes, winding, frame.params, scene_referred=True)
    reference = read_hdr(pipeline / "reference.exr").pixels
    tolerance = mantissa_tolerance(reference, frame.params.gain, bits=8, alpha=2.0)
    assert np.all(np.abs(x_hat - reference) <= tolerance)


def test_simulate_rgb_tiff_with_noise_and_max_wraps(tmp_path: Path) -> None:
    write_exr(tmp_path / "rgb.exr", blob_scene(size=24, rgb=True))
    result = run_mcam(
        "simulate", "rgb.exr", "-o", "rgb.tiff", "--encoding", "modulo", "--bits", "12",
        "--gain", "0.5", "--max-wraps", "16", "--read-noise", "0.001", "--seed", "3",
        "--reference-out", "ref.exr",
        cwd=tmp_path,
    )  # fmt: skip
    assert result.returncode == 0, result.stderr
    frame = read_frame(tmp_path / "rgb.tiff")
    assert frame.codes.shape == (24, 24, 3)
    assert frame.params.max_wraps == 16.0
    assert frame.params.seed == 3
    # the reference is what the sensor saw: x clipped at max_wraps, back in scene units
    assert read_hdr(tmp_path / "ref.exr").pixels.max() == 16.0 / 0.5


def test_a_reference_float32_would_store_as_zero_is_refused(tmp_path: Path) -> None:
    """x clipped at 2.5 wraps over a gain of 1e50 is 2.5e-50 in scene units, below
    float32's smallest: the reference was written all 0, in silence. (Not 3 wraps: a
    frame clipped everywhere at a whole wrap stores code 0 and is refused first.)"""
    write_exr(tmp_path / "scene.exr", blob_scene(size=16))
    result = run_mcam(
        "simulate", "scene.exr", "-o", "f.npy", "--encoding", "modulo", "--gain", "1e50",
        "--max-wraps", "2.5", "--reference-out", "ref.exr",
        cwd=tmp_path,
    )  # fmt: skip
    assert_one_line_error(result, "256 nonzero pixels", "stored as 0", "gain 1e+50")
    assert not (tmp_path / "ref.exr").exists()


def test_simulate_without_seed_draws_the_noise_of_seed_0(tmp_path: Path) -> None:
    write_exr(tmp_path / "scene.exr", blob_scene(size=16))
    noisy = ("--read-noise", "0.05", "--full-well", "1000")
    for name, seed in (("a.png", ()), ("b.png", ()), ("c.png", ("--seed", "0"))):
        result = run_mcam("simulate", "scene.exr", "-o", name, *noisy, *seed, cwd=tmp_path)
        assert result.returncode == 0, result.stderr
    frames = [read_frame(tmp_path / name) for name in ("a.png", "b.png", "c.png")]
    assert all(frame.params.seed == 0 for frame in frames)
    np.testing.assert_array_equal(frames[0].codes, frames[1].codes)
    np.testing.assert_array_equal(frames[0].codes, frames[2].codes)


def test_simulate_bad_input(tmp_path: Path) -> None:
    write_exr(tmp_path / "rgb.exr", blob_scene(size=16, rgb=True))
    assert_one_line_error(
        run_mcam("simulate", "rgb.exr", "-o", "w.png", "--gain", "1", cwd=tmp_path), ".tiff"
    )
    assert_one_line_error(
        run_mcam("simulate", "rgb.exr", "-o", "w.tiff", "--alpha", "0.5", cwd=tmp_path), "alpha"
    )


def test_overexposed_near_or_at_1_is_explained(tmp_path: Path) -> None:
    """At 0.999 on a scene whose clipped negatives are 2% of it, it said 'the brightest
    100% of pixels have zero luminance'; at 1.0, 'overexposed must be in (0, 1)'."""
    scene = blob_scene(size=50)
    scene.flat[::50] = -1e-3  # 50 of 2500 pixels: lossy EXR's negatives
    write_exr(tmp_path / "scene.exr", scene)
    flags = ("simulate", "scene.exr", "-o", "w.png", "--clip-negative", "--overexposed")
    near = run_mcam(*flags, "0.999", cwd=tmp_path)
    assert_one_line_error(
        near, "50 of 2500 pixels (2%) have zero luminance", "negative values clipped to 0",
        "give overexposed at most 0.98",
    )  # fmt: skip
    at_1 = run_mcam(*flags, "1.0", cwd=tmp_path)
    assert_one_line_error(at_1, "strictly between 0 and 1", "got 1:", "or the gain instead")
    assert not (tmp_path / "w.png").exists()
    largest = run_mcam(*flags, "0.98", cwd=tmp_path)
    assert largest.returncode == 0, largest.stderr
    assert "clipped 50 negative scene values to 0" in largest.stdout


def test_simulate_checks_every_output_before_writing_any(tmp_path: Path) -> None:
    write_exr(tmp_path / "scene.exr", blob_scene(size=16))
    bad_suffix = run_mcam("simulate", "scene.exr", "-o", "w.png", "--ground-truth", "W.exr",
                          cwd=tmp_path)  # fmt: skip
    assert_one_line_error(bad_suffix, "--ground-truth W.exr", ".png")
    same = run_mcam("simulate", "scene.exr", "-o", "w.png", "--ground-truth", "w.png",
                    cwd=tmp_path)  # fmt: skip
    assert_one_line_error(same, "-o and --ground-truth both name w.png")
    over_input = run_mcam("simulate", "scene.exr", "-o", "w.png", "--reference-out", "scene.exr",
                          cwd=tmp_path)  # fmt: skip
    assert_one_line_error(over_input, "--reference-out scene.exr is the input file")
    assert sorted(path.name for path in tmp_path.iterdir()) == ["scene.exr"]


def test_simulate_refuses_a_frame_that_quantises_to_black(tmp_path: Path) -> None:
    write_exr(tmp_path / "dim.exr", np.full((8, 8), 1e-30))
    result = run_mcam("simulate", "dim.exr", "-o", "w.png", cwd=tmp_path)
    assert_one_line_error(result, "every pixel quantises to code 0", "--overexposed")
    assert not (tmp_path / "w.png").exists()


def test_simulate_npy_prints_the_flags_reconstruct_needs(tmp_path: Path) -> None:
    write_exr(tmp_path / "scene.exr", blob_scene(size=16))
    result = run_mcam("simulate", "scene.exr", "-o", "w.npy", "--bits", "10", "--gain", "0.25",
                      cwd=tmp_path)  # fmt: skip
    assert result.returncode == 0, result.stderr
    flags = "--encoding mantissa --alpha 2.0 --bits 10 --gain 0.25"
    assert f"w.npy holds the codes only: reconstruct it with {flags}" in result.stdout
    rebuilt = run_mcam("reconstruct", "w.npy", "-o", "x.exr", *flags.split(), cwd=tmp_path)
    assert rebuilt.returncode == 0, rebuilt.stderr
