"""Tests of bench/colour.py: the colour sets, the decoder pairs and the report."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from bench import colour
from models.decoders.adaptive import AdaptiveDecoder
from models.decoders.colour import ColourDecoder
from models.metrics import PSNR_CAP


def test_the_tuning_set_holds_two_crops_of_every_training_scene_apart_from_val() -> None:
    tuning = colour.frame_set("tuning", "modulo")
    assert len(tuning) == 2 * 14
    assert all(frame.codes.shape == (256, 256, 3) for frame in tuning[:3])
    assert len(colour.frame_set("val", "modulo")) == 24


@pytest.mark.parametrize("name", ["herraez", "auto-best"])
def test_each_decoder_is_measured_alone_and_made_consistent(name: str) -> None:
    alone, joint = colour.pair(name)
    if name.startswith("auto"):
        assert isinstance(alone, AdaptiveDecoder) and isinstance(joint, AdaptiveDecoder)
        assert not alone.joint_colour and joint.joint_colour
    else:
        assert isinstance(joint, ColourDecoder) and joint.inner is alone


def test_report_compares_both_modes_frame_by_frame(tmp_path: Path) -> None:
    out = tmp_path / "colour.json"
    colour.main(["--decoders", "itoh", "--encodings", "mantissa", "--sets", "val",
                 "--frames", "2", "--out", str(out)])  # fmt: skip
    report = json.loads(out.read_text())
    assert len(report["load_average"]) == 3 and report["versions"]["numpy"]
    row = report["rows"][0]
    assert (row["set"], row["encoding"], row["decoder"]) == ("val", "mantissa", "itoh")
    for mode in ("alone", "joint"):
        assert len(row[mode]["psnr_per_frame_db"]) == 2
        assert 0.0 <= row[mode]["all_channels_right"] <= row[mode]["winding_accuracy"] <= 1.0
        assert row[mode]["ms_per_frame"] > 0
    assert row["frames"] == 2
    assert out.with_suffix(".md").read_text().count("| val | mantissa | itoh | 2 |") == 1


def test_auto_is_measured_as_auto_balanced_alone_and_joint() -> None:
    """``auto`` got the registry's shared decoder, joint already, as 'alone'."""
    alone, joint = colour.pair("auto")
    assert isinstance(alone, AdaptiveDecoder) and isinstance(joint, AdaptiveDecoder)
    assert (alone.quality, alone.joint_colour, joint.joint_colour) == ("balanced", False, True)


@pytest.mark.parametrize("name", ["itoh+colour", "auto-50ms"])
def test_decoders_joint_already_are_a_usage_error(
    name: str, capsys: pytest.CaptureFixture[str]
) -> None:
    with pytest.raises(SystemExit) as exited:
        colour.parse_args(["--decoders", "itoh", name])
    assert exited.value.code == 2
    assert f"decoders {name} make the channels consistent themselves" in capsys.readouterr().err


def test_an_exact_frame_counts_at_the_psnr_cap_in_means_and_changes() -> None:
    """It was left out of both: a frame exact alone and at 30 dB made consistent counted
    as no loss, and the alone mean read 30 dB."""
    decoded = {"winding_accuracy": 1.0, "all_channels_right": 1.0, "ms_per_frame": 1.0}
    alone = {**decoded, "psnr_db": [float("inf"), 30.0], "pu21_psnr_db": [float("inf"), 30.0]}
    joint = {**decoded, "psnr_db": [30.0, 30.0], "pu21_psnr_db": [30.0, 30.0]}
    row = colour.summary(alone, joint)
    assert row["alone"]["psnr_db"] == row["alone"]["pu21_psnr_db"] == (PSNR_CAP + 30.0) / 2
    assert row["worst_frame_change_db"] == 30.0 - PSNR_CAP
    assert row["frames_losing_0_5_db"] == 1
