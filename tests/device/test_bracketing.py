"""Bracket merge (Debevec hat weights, linear sensor) and bracket assembly."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from device.bracketing import (
    DARK_LEVEL,
    SATURATION_LEVEL,
    Bracket,
    BracketCollector,
    SaturatedBracketError,
    clipped_pixels,
    hat_weight,
    merge_exposures,
    save_pair,
)
from device.datasets import device_dir
from device.link_protocol import FLAG_BRACKET, DataPacket
from models.errors import InvalidInputError, OutputOverflowError
from models.formation import SensorParams, simulate

GAINS = [1 / 16, 1 / 8, 1 / 4, 1 / 2, 1.0]


def clipped(scene: np.ndarray, gain: float, bits: int = 8, **noise: float) -> np.ndarray:
    return simulate(scene, SensorParams(encoding="clip", bits=bits, gain=gain, seed=1,
                                        **noise)).codes


def test_hat_weight_is_zero_for_dark_and_saturated_and_peaks_in_between() -> None:
    z = np.array([0.0, DARK_LEVEL, (DARK_LEVEL + SATURATION_LEVEL) / 2, SATURATION_LEVEL, 1.0])
    np.testing.assert_allclose(hat_weight(z), [0, 0, 1, 0, 0], atol=1e-12)


@given(scene=st.floats(0.25, 15.9), bits=st.integers(8, 12))
@settings(max_examples=60, deadline=None)
def test_noise_free_merge_is_within_quantization(scene: float, bits: int) -> None:
    """Stated accuracy: within 4 code steps (4 / 2^bits relative) where the brightest
    exposure reaches z >= 1/4; darker pixels rely on low codes (17 / 2^bits at z = 0.03)."""
    image = np.full((2, 2), scene)
    merged = merge_exposures([clipped(image, g, bits) for g in GAINS], GAINS, bits)
    np.testing.assert_allclose(merged, scene, rtol=4.0 / (1 << bits))


def test_noisy_merge_accuracy_on_a_ramp() -> None:
    scene = np.geomspace(0.05, 14.0, 256 * 64).reshape(64, 256)
    codes = [clipped(scene, g, read_noise=0.002, full_well=20_000.0) for g in GAINS]
    relative = np.abs(merge_exposures(codes, GAINS, 8) - scene) / scene
    # Stated accuracy with noise: above 1/4 of the brightest exposure's saturation, median
    # < 1 % and 99th percentile < 3 %; below it (z < 0.25 everywhere) 99th percentile < 10 %.
    bright = scene >= 0.25
    assert np.median(relative[bright]) < 0.01 and np.quantile(relative[bright], 0.99) < 0.03
    assert np.quantile(relative[~bright], 0.99) < 0.10


def test_unusable_pixels_fall_back_to_the_extreme_exposures() -> None:
    scene = np.array([[1e-4, 1e3]])
    merged = merge_exposures([clipped(scene, g) for g in GAINS], GAINS, 8)
    assert merged[0, 0] < DARK_LEVEL  # brightest exposure's (dark) estimate
    assert merged[0, 1] == pytest.approx(16.0, rel=0.01)  # saturated: lower bound 1 / (1/16)


def test_merge_rejects_bad_brackets() -> None:
    with pytest.raises(InvalidInputError, match="at least two"):
        merge_exposures([np.zeros((2, 2), np.uint8)], [1.0], 8)
    with pytest.raises(InvalidInputError, match="positive"):
        merge_exposures([np.zeros((2, 2), np.uint8)] * 2, [1.0, 0.0], 8)


def packet(seq: int, index: int, count: int = 3, flags: int = FLAG_BRACKET) -> DataPacket:
    return DataPacket(seq, 0, "clip" if index else "modulo", 2.0, 8, 0.5 * 2**index,
                      np.zeros((2, 2), np.uint8), flags, index, count)


def test_collector_assembles_consecutive_packets_and_abandons_broken_ones() -> None:
    collector = BracketCollector()
    assert collector.add(packet(9, 0, flags=0)) is None
    assert collector.add(packet(10, 0)) is None
    assert collector.add(packet(11, 1)) is None
    bracket = collector.add(packet(12, 2))
    assert bracket is not None and bracket.wrapped.sequence == 10
    assert [p.sequence for p in bracket.exposures] == [11, 12]
    collector.add(packet(20, 0))
    assert collector.add(packet(22, 1)) is None  # a gap: abandoned
    collector.add(packet(30, 0))
    collector.interrupt()
    assert collector.abandoned == 2


def exposure(seq: int, index: int, shape: tuple[int, int] = (2, 2), bits: int = 8,
             encoding: str = "clip") -> DataPacket:
    return DataPacket(seq, 0, encoding, 2.0, bits, 0.5 * 2**index,
                      np.zeros(shape, np.uint16 if bits > 8 else np.uint8), FLAG_BRACKET, index, 3)


@pytest.mark.parametrize("misfit", [
    {"shape": (4, 4)}, {"bits": 12}, {"encoding": "modulo"},
])
def test_an_exposure_that_does_not_fit_abandons_the_bracket(misfit: dict) -> None:
    """An exposure of another size than the wrapped frame, another bit depth than the
    exposure before it, or not a conventional image cannot be merged into the pair's
    reference: the bracket is abandoned (counted), not stored or crashed on."""
    collector = BracketCollector()
    collector.add(packet(10, 0))
    assert collector.add(exposure(11, 1)) is None
    assert collector.add(exposure(12, 2, **misfit)) is None
    assert collector.abandoned == 1
    collector.add(packet(20, 0))
    collector.add(exposure(21, 1))
    assert collector.add(exposure(22, 2)) is not None


def bracket_of(gain: float, codes: np.ndarray | None = None) -> Bracket:
    """A 4-exposure bracket of an 8 x 8 scene, mid-grey unless every exposure reads
    ``codes``, the wrapped frame at ``gain``."""
    codes = np.full((8, 8), 128, np.uint8) if codes is None else codes

    def packet(index: int, encoding: str, packet_gain: float) -> DataPacket:
        return DataPacket(100 + index, 0, encoding, 2.0, 8, packet_gain, codes, FLAG_BRACKET,
                          index, 4)

    exposures = [packet(i, "clip", gain / 2 ** (3 - i)) for i in (1, 2, 3)]
    return Bracket(packet(0, "modulo", gain), exposures)


def test_a_pair_is_saved_whole(tmp_path: Path) -> None:
    folder = save_pair(tmp_path, "cam", bracket_of(1.0))
    assert sorted(path.name for path in folder.iterdir()) == [
        "meta.json", "reference.exr", "wrapped.png"]
    assert list(device_dir(tmp_path, "cam").iterdir()) == [folder]


def test_a_pair_whose_reference_cannot_be_written_leaves_no_folder(tmp_path: Path) -> None:
    """Gains near 1e-300 put the reference past float32: the EXR is refused after
    wrapped.png was written, and no folder (finished or not) is left."""
    save_pair(tmp_path, "cam", bracket_of(1.0))
    with pytest.raises(OutputOverflowError, match="float32"):
        save_pair(tmp_path, "cam", bracket_of(1e-300))
    assert len(list(device_dir(tmp_path, "cam").iterdir())) == 1


def test_a_bracket_saturated_at_every_pixel_is_refused_and_nothing_written(
    tmp_path: Path,
) -> None:
    """Its reference would be the darkest exposure's clip everywhere (was saved as a
    pair, with nothing to tell a training set that its target holds no measurement)."""
    saturated = bracket_of(1.0, np.full((8, 8), 250, np.uint8))
    assert saturated.clipped().all()
    with pytest.raises(SaturatedBracketError, match="every pixel is saturated.*gain 0.25"):
        save_pair(tmp_path, "cam", saturated)
    assert not device_dir(tmp_path, "cam").exists()


def test_a_pair_records_the_share_of_pixels_saturated_in_every_exposure(
    tmp_path: Path,
) -> None:
    codes = np.full((8, 8), 128, np.uint8)
    codes[:2] = 255
    folder = save_pair(tmp_path, "cam", bracket_of(1.0, codes))
    meta = json.loads((folder / "meta.json").read_text())
    assert meta["merge"]["clipped_fraction"] == 0.25


def test_clipped_pixels_are_those_no_exposure_measured_below_saturation() -> None:
    """Saturated in the darkest exposure but below saturation in a brighter one (noise):
    measured, not clipped; dark in every exposure: an estimate, not clipped."""
    darkest = np.array([[255, 255, 0, 128]], np.uint8)
    brighter = np.array([[255, 200, 0, 255]], np.uint8)
    clipped = clipped_pixels([brighter, darkest], [1.0, 0.5], 8)
    np.testing.assert_array_equal(clipped, [[True, False, False, False]])


@pytest.mark.parametrize("count", [1, 2])
def test_a_bracket_of_fewer_than_two_exposures_says_so(tmp_path: Path, count: int) -> None:
    """A camera that sends bracket count 1 (the wrapped frame alone) or 2 completes a
    bracket no reference can be merged from: the refusal says how many exposures it had
    and what the camera sent (count 1 read 'bracket exposures mix bit depths []')."""
    collector = BracketCollector()
    brackets = [collector.add(packet(10 + i, i, count)) for i in range(count)]
    assert brackets[-1] is not None
    with pytest.raises(InvalidInputError, match=f"at least two clipped exposures, this one has "
                       f"{count - 1} .*bracket count {count}"):
        save_pair(tmp_path, "cam1", brackets[-1])
    assert not (tmp_path / "datasets").exists()
