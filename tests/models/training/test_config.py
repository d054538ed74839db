"""Tests of models/training/config.py: run names, data shares, and the checks made
before a run trains."""

from __future__ import annotations

import math

import pytest
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
