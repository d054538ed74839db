"""Tests of models/training/recipes.py: the shipped recipes are trainable in order."""

from __future__ import annotations

import json

from models.decoders.learned import ONNX_DIR
from models.training.config import TrainConfig
from models.training.recipes import SHIPPED, exported, quantized


def test_every_run_that_starts_from_another_comes_after_it() -> None:
    names = [config.name for config in SHIPPED]
    for index, config in enumerate(SHIPPED):
        if config.init_from:
            assert config.init_from in names[:index], config.name


def test_run_names_are_unique() -> None:
    names = [config.name for config in SHIPPED]
    assert len(names) == len(set(names))


def test_a_labelled_run_is_a_step_towards_a_later_one_and_not_exported() -> None:
    """A labelled run is not exported, and the runs that start from it (directly or
    through other labelled runs) end in an exported one."""
    for index, config in enumerate(SHIPPED):
        if config.label:
            assert not exported(config)
            assert config.label in config.name
            reached, steps = {config.name}, []
            for later in SHIPPED[index + 1 :]:
                if later.init_from in reached:
                    reached.add(later.name)
                    steps.append(later)
            assert [c for c in steps if exported(c)], config.name


def test_only_plain_small_models_are_quantized() -> None:
    assert quantized(TrainConfig(tier="small"))
    assert not quantized(TrainConfig(tier="small", max_read_noise=0.02))
    assert not quantized(TrainConfig(tier="tiny"))


def test_every_shipped_card_was_trained_by_its_recipe() -> None:
    """``mcam train all`` reproduces the shipped models: each card records the stage
    steps, read noise, starting run, loss, crops, batch and precision of its recipe."""
    for config in filter(exported, SHIPPED):
        card_path = ONNX_DIR / f"{config.name}.json"
        assert card_path.exists(), f"no shipped card for recipe {config.name}"
        training = json.loads(card_path.read_text())["training"]
        assert tuple(training["planned_stage_steps"]) == config.stage_steps, config.name
        assert training["max_read_noise"] == config.max_read_noise, config.name
        assert training.get("init_from") == config.init_from, config.name
        assert training["loss"] == config.loss, config.name
        assert (training["crop"], training["batch"]) == (config.crop, config.batch), config.name
        # Cards written before these were recorded: 128-px large crops, float32.
        assert training.get("large_crop", 128) == config.large_crop, config.name
        assert training.get("precision", "fp32") == config.precision, config.name
        assert training.get("own_states", 0.0) == config.own_states, config.name
        if config.family == "unmodnet":
            assert training["own_passes"] == config.own_passes, config.name
