"""Tests of models/scenes.py: HDRI loading, the split, val-256 and synthetic scenes."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from models import scenes
from models.errors import InvalidInputError
from models.exposure import luminance
from models.formation import reconstruct


def test_split_is_disjoint_and_complete() -> None:
    assert set(scenes.VAL_SCENES).isdisjoint(scenes.TRAIN_SCENES)
    assert len(scenes.SCENE_NAMES) == 17
    assert {p.stem for p in scenes.HDRI_DIR.glob("*.exr")} == set(scenes.SCENE_NAMES)


def test_load_hdri_is_non_negative_rgb() -> None:
    rgb = scenes.load_hdri("forest")
    assert rgb.shape == (256, 512, 3) and rgb.dtype == np.float64
    assert np.isfinite(rgb).all() and rgb.min() >= 0
    assert scenes.clipped_negatives("forest") > 0
    assert scenes.load_hdri_gray("forest").shape == (256, 512)


@pytest.fixture
def scene_folder(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[Path]:
    """An empty scene folder in place of models/data/hdri (the loaded scenes forgotten
    before and after)."""
    scenes._load_hdri.cache_clear()
    monkeypatch.setattr(scenes, "HDRI_DIR", tmp_path)
    yield tmp_path
    scenes._load_hdri.cache_clear()


def test_a_missing_scene_says_how_to_restore_the_shipped_ones(scene_folder: Path) -> None:
    """It said 'no such folder: ...; create it or choose another path' (for the CLI)."""
    with pytest.raises(FileNotFoundError, match="scene 'park' is missing .*git checkout"):
        scenes.load_hdri("park")


def test_an_unreadable_scene_says_how_to_restore_the_shipped_ones(scene_folder: Path) -> None:
    """It said the file was not an OpenEXR image: 'convert it to OpenEXR'."""
    (scene_folder / "park.exr").write_text("not an image")
    with pytest.raises(InvalidInputError, match="scene .park. cannot be read .*git") as caught:
        scenes.load_hdri("park")
    assert "park.exr" in caught.value.message and "convert" not in caught.value.message


def test_unknown_scene_is_a_clear_error() -> None:
    with pytest.raises(InvalidInputError, match="unknown scene"):
        scenes.load_hdri("nowhere")


@pytest.mark.parametrize("encoding", ["mantissa", "modulo"])
def test_val256_frames_follow_the_protocol(encoding: str) -> None:
    frames = scenes.val256_frames(encoding)
    assert len(frames) >= 24
    for frame in frames[:3]:
        codes, winding, x, params = frame
        assert codes.shape == winding.shape == x.shape == (256, 256)
        assert codes.dtype == np.uint8 and params.bits == 8 and params.max_wraps == 16
        assert abs((x > 1).mean() - 0.2) < 0.01
        assert x.max() <= 16
        np.testing.assert_allclose(reconstruct(codes, winding, params), x, rtol=0.02, atol=1 / 256)


def test_val256_is_deterministic_and_noise_changes_codes() -> None:
    first, again = scenes.val256_frames("mantissa")[0], scenes.val256_frames("mantissa")[0]
    np.testing.assert_array_equal(first.codes, again.codes)
    noisy = scenes.val256_frames("mantissa", read_noise=0.01)[0]
    assert noisy.params.read_noise == 0.01
    assert (noisy.codes != first.codes).mean() > 0.1


def test_crop_offsets_are_distinct_and_in_range() -> None:
    offsets = scenes.val256_crop_offsets(512, 8, 1)
    assert len(set(offsets)) == 8 and min(offsets) >= 0 and max(offsets) < 512


@settings(max_examples=10, deadline=None)
@given(seed=st.integers(0, 2**31), size=st.sampled_from([16, 48, 64]))
def test_synthetic_scene_is_seeded_finite_and_positive(seed: int, size: int) -> None:
    scene = scenes.synthetic_scene(seed, size)
    assert scene.shape == (size, size)
    assert np.isfinite(scene).all() and scene.min() > 0
    np.testing.assert_array_equal(scene, scenes.synthetic_scene(seed, size))


@pytest.mark.parametrize("encoding", ["mantissa", "modulo"])
def test_synthetic_val256_frame_is_seeded_and_exposed_like_val256(encoding: str) -> None:
    frame = scenes.synthetic_val256_frame(encoding, 64, seed=3)
    again = scenes.synthetic_val256_frame(encoding, 64, seed=3)
    assert frame.codes.shape == (64, 64) and np.array_equal(frame.codes, again.codes)
    assert frame.params.encoding == encoding and frame.params.bits == scenes.VAL256_BITS
    assert frame.params.max_wraps == scenes.VAL256_MAX_WRAPS
    assert (frame.irradiance > 1.0).mean() == pytest.approx(scenes.VAL256_OVEREXPOSED, abs=0.02)


def test_val256_in_colour_is_the_same_crops_exposed_on_their_luminance() -> None:
    gray, colour = scenes.val256_frames("mantissa")[:2], scenes.val256_frames(
        "mantissa", colour=True
    )
    assert len(colour) == len(scenes.val256_frames("mantissa"))
    crops = scenes.val256_scenes(colour=True)
    for frame, (label, crop), (gray_label, gray_crop) in zip(
        colour[:2], crops, scenes.val256_scenes(), strict=False
    ):
        assert label == gray_label and crop.shape == (256, 256, 3)
        np.testing.assert_allclose(luminance(crop), gray_crop)
        assert frame.codes.shape == frame.winding.shape == (256, 256, 3)
        assert abs((luminance(frame.x) > 1).mean() - 0.2) < 0.01
    assert gray[0].params.gain == pytest.approx(colour[0].params.gain)


def test_the_colour_synthetic_frame_is_the_scene_tinted_and_exposed_on_luminance() -> None:
    frame = scenes.synthetic_val256_frame("mantissa", 64, seed=3, colour=True)
    again = scenes.synthetic_val256_frame("mantissa", 64, seed=3, colour=True)
    assert frame.codes.shape == (64, 64, 3) and np.array_equal(frame.codes, again.codes)
    overexposed = (luminance(frame.irradiance) > 1.0).mean()
    assert overexposed == pytest.approx(scenes.VAL256_OVEREXPOSED, abs=0.02)
    tint = scenes.synthetic_tint(3, 64)
    assert np.all(tint[:, :, 1] == 1.0)
    assert np.all(np.abs(np.log(tint)) <= 0.6) and np.ptp(np.log(tint[:, :, 0])) > 0.0


@pytest.mark.parametrize("seed", [0, 7])
def test_lobes_only_add_smooth_light_to_the_same_scene(seed: int) -> None:
    """A scene with lobes is the scene without them plus bright smooth light: brighter
    nowhere darker, seeded, and reaching at least 10x the plain scene's median."""
    plain = scenes.synthetic_scene(seed, 64)
    lit = scenes.synthetic_scene(seed, 64, lobes=True)
    np.testing.assert_array_equal(lit, scenes.synthetic_scene(seed, 64, lobes=True))
    assert np.all(lit >= plain) and np.isfinite(lit).all()
    assert (lit - plain).max() > 0


def test_glows_cross_every_wrap_up_to_their_peak() -> None:
    """A lobe decays smoothly: neighbouring pixels differ by far less than the peak, so
    its rings can be counted (the reason to train on it)."""
    light = scenes.glows(np.random.default_rng(3), 128, 1.0)
    assert light.min() >= 0 and light.max() >= 10.0
    steps = np.abs(np.diff(np.log(light + 1.0), axis=1))
    assert steps.max() < 0.5 * np.log(light.max() + 1.0)
