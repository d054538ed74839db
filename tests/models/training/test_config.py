"""Tests of models/training/config.py: run names, data shares, and the checks made
before a run trains."""

from __future__ import annotations

import math

import pytest
import torch
from pydantic import ValidationError

from models.errors import InvalidInputError
from models.formation import SensorParams
from models.scenes import TRAIN_SCENES, load_hdri_gray
from models.training.config import READ_NOISE_LIMIT, TrainConfig, check_config
from models.training.data import largest_crop


def test_a_label_names_the_run_but_not_the_decoder() -> None:
    config = TrainConfig(tier="small-s2d", encoding="modulo", label="part1")
    assert config.name == "mantissanet-small-s2d-part1-modulo"
    assert config.decoder == "mantissanet-small-s2d"
    assert TrainConfig(tier="small-s2d").name == "mantissanet-small-s2d-mantissa"


def test_colour_channel_data_names_the_run_and_the_decoder() -> None:
    config = TrainConfig(tier="tiny", colour_fraction=0.5, max_read_noise=0.01, label="ft")
    assert config.name == "mantissanet-tiny-noise-colour-ft-mantissa"
    assert config.decoder == "mantissanet-tiny-noise-colour"
    assert config.pairs(3).colour_fraction == config.pairs(4).colour_fraction == 0.5


@pytest.mark.parametrize("field", ["colour_fraction", "glow_fraction"])
@pytest.mark.parametrize("fraction", [-0.1, 1.5, float("nan")])
def test_a_data_fraction_outside_0_1_is_refused(field: str, fraction: float) -> None:
    with pytest.raises(InvalidInputError, match=field):
        check_config(TrainConfig(**{field: fraction}))


def test_the_glow_fraction_reaches_every_stages_pairs() -> None:
    config = TrainConfig(tier="tiny", glow_fraction=0.25)
    assert config.pairs(3).glow_fraction == config.pairs(4).glow_fraction == 0.25


def test_the_read_noise_limit_is_the_sensor_models() -> None:
    SensorParams(encoding="mantissa", read_noise=READ_NOISE_LIMIT)
    with pytest.raises(ValidationError):
        SensorParams(encoding="mantissa", read_noise=math.nextafter(READ_NOISE_LIMIT, 2.0))


def test_the_largest_crop_is_the_smallest_panoramas_side() -> None:
    assert largest_crop() == min(min(load_hdri_gray(name).shape) for name in TRAIN_SCENES)


def test_a_gpu_number_the_machine_lacks_is_refused(monkeypatch: pytest.MonkeyPatch) -> None:
    """On a one-GPU machine, cuda:5 passed the checks (only is_available was asked), so
    the run went on to move its model to a device that does not exist."""
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 1)
    with pytest.raises(InvalidInputError, match="'cuda:5' asked for, but torch sees 1 CUDA"):
        check_config(TrainConfig(device="cuda:5"))
    check_config(TrainConfig(device="cuda:0"))
    check_config(TrainConfig(device="cuda"))
