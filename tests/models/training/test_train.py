"""Tests of models/training/train.py: a tiny seeded run, its log, and resuming."""

from __future__ import annotations

import json
import math
from dataclasses import replace
from pathlib import Path

import pytest
import torch

from models.training.networks import TIERS, UnModNet
from models.training.train import (
    HEAD_OUTPUTS,
    RISK_FLOOR,
    TrainConfig,
    checkpoint_segments,
    expected_log_mse,
    load_checkpoint,
    prediction_accuracy,
    rolled_out_state,
    rollover_losses,
    train,
    winding_jumps,
    winding_loss,
)


def tiny_config(runs: Path, steps: tuple[int, int, int]) -> TrainConfig:
    return TrainConfig(
        tier="tiny", stage_steps=steps, crop=32, batch=2, runs_dir=runs,
        checkpoint_every=2, log_every=1,
    )  # fmt: skip


def test_three_stages_log_and_checkpoint(tmp_path: Path) -> None:
    config = tiny_config(tmp_path, (1, 1, 1))
    checkpoint = train(config)
    records = [json.loads(line) for line in (config.run_dir / "log.jsonl").read_text().splitlines()]
    assert [r["stage"] for r in records] == [1, 2, 3]
    assert "edge_bce" in records[0] and "accuracy" in records[1] and "accuracy" in records[2]
    assert all(r["loss"] > 0 for r in records)
    assert load_checkpoint(checkpoint)["step"] == 3


def test_resumed_run_equals_an_uninterrupted_one(tmp_path: Path) -> None:
    whole = load_checkpoint(train(tiny_config(tmp_path / "a", (1, 2, 1))))
    train(tiny_config(tmp_path / "b", (1, 1, 0)))
    resumed = load_checkpoint(train(tiny_config(tmp_path / "b", (1, 2, 1))))
    assert resumed["step"] == whole["step"] == 4
    for key, value in whole["model"].items():
        torch.testing.assert_close(resumed["model"][key], value)


def test_unknown_loss_is_refused(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="loss must be one of"):
        train(TrainConfig(loss="l1", runs_dir=tmp_path))


def test_negative_risk_weight_is_refused(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="risk_weight must be >= 0"):
        train(TrainConfig(loss="ce-risk", risk_weight=-1.0, runs_dir=tmp_path))


@pytest.mark.parametrize("loss", ["ce-risk", "mse", "jumps"])
def test_every_loss_trains_and_names_its_run(tmp_path: Path, loss: str) -> None:
    config = TrainConfig(
        tier="tiny", loss=loss, stage_steps=(1, 1, 1), crop=32, batch=2, runs_dir=tmp_path
    )
    assert config.name == f"mantissanet-tiny-{loss}-mantissa"
    assert config.decoder == "mantissanet-tiny"
    state = load_checkpoint(train(config))
    head = state["model"]["winding.head.weight"]
    assert head.shape[0] == HEAD_OUTPUTS[loss]


def test_a_label_names_the_run_but_not_the_decoder() -> None:
    config = TrainConfig(tier="small-s2d", encoding="modulo", label="part1")
    assert config.name == "mantissanet-small-s2d-part1-modulo"
    assert config.decoder == "mantissanet-small-s2d"
    assert TrainConfig(tier="small-s2d").name == "mantissanet-small-s2d-mantissa"


def test_jumps_loss_is_zero_for_the_true_jumps_and_counts_them_right() -> None:
    winding = torch.tensor([[0, 0, 2], [0, 1, 3], [1, 1, 3]]).reshape(1, 1, 3, 3)
    along_cols, along_rows = winding_jumps(winding)
    output = torch.zeros(1, 2, 3, 3)
    output[:, :1, :, :-1] = along_cols
    output[:, 1:, :-1] = along_rows
    assert winding_loss(output, winding, "jumps").item() == 0.0
    assert prediction_accuracy(output, winding, "jumps").item() == 1.0
    output[0, 0, 0, 1] += 1.0
    assert winding_loss(output, winding, "jumps").item() > 0.0
    assert prediction_accuracy(output, winding, "jumps").item() == pytest.approx(11 / 12)


def test_a_run_can_start_from_another_runs_weights(tmp_path: Path) -> None:
    source = train(tiny_config(tmp_path, (1, 1, 1)))
    config = TrainConfig(
        tier="tiny", stage_steps=(0, 0, 0, 0), crop=32, batch=2, runs_dir=tmp_path,
        max_read_noise=0.02, init_from="mantissanet-tiny-mantissa",
    )  # fmt: skip
    started = load_checkpoint(train(config))
    assert config.name == "mantissanet-tiny-noise-mantissa" and started["step"] == 0
    for key, value in load_checkpoint(source)["model"].items():
        torch.testing.assert_close(started["model"][key], value)


def test_a_missing_initial_run_is_named_in_the_error(tmp_path: Path) -> None:
    config = TrainConfig(tier="tiny", stage_steps=(0, 0, 0, 1), runs_dir=tmp_path,
                         init_from="mantissanet-nothing")  # fmt: skip
    with pytest.raises(FileNotFoundError, match="train mantissanet-nothing first"):
        train(config)



def test_ce_risk_adds_the_expected_log_mse_and_needs_the_errors() -> None:
    logits = torch.randn(2, HEAD_OUTPUTS["ce"], 4, 4, generator=torch.Generator().manual_seed(0))
    winding = torch.randint(0, HEAD_OUTPUTS["ce"], (2, 1, 4, 4))
    plain = winding_loss(logits, winding, "ce")
    errors = torch.zeros(2, HEAD_OUTPUTS["ce"], 4, 4)
    floor = math.log(RISK_FLOOR)
    torch.testing.assert_close(winding_loss(logits, winding, "ce-risk", errors, 2.0),
                               plain + 2.0 * floor)  # fmt: skip
    with pytest.raises(ValueError, match="needs the per-class errors"):
        winding_loss(logits, winding, "ce-risk")


def test_expected_log_mse_is_the_log_of_the_probability_weighted_error() -> None:
    # Two classes, one pixel: p = (0.75, 0.25) on errors (0, 8) expects an MSE of 2.
    logits = torch.log(torch.tensor([0.75, 0.25])).reshape(1, 2, 1, 1)
    errors = torch.tensor([0.0, 8.0]).reshape(1, 2, 1, 1)
    expected = math.log(2.0 + RISK_FLOOR)
    assert expected_log_mse(logits, errors).item() == pytest.approx(expected, rel=1e-6)


def test_rolled_out_passes_stay_inside_the_previous_ones() -> None:
    torch.manual_seed(0)
    model = UnModNet(TIERS["tiny"]).eval()
    m = torch.rand(2, 1, 32, 32)
    edges = model.edge(m)
    states = [rolled_out_state(model, m, edges, passes) for passes in range(4)]
    assert not states[0].any()
    for before, after in zip(states, states[1:], strict=False):
        grew = after - before
        assert set(grew.unique().tolist()) <= {0.0, 1.0}
    for previous, before, after in zip(states, states[1:], states[2:], strict=False):
        assert torch.all((after - before) <= (before - previous))


def test_own_states_train_from_the_models_answer() -> None:
    """With ``own_states = 1`` every batch starts from the model's own rolled-out state,
    so the targets are where the true W is above that state; with 0 the random
    ``min(W, k)`` states are used and the generator draws the same numbers as before."""
    torch.manual_seed(0)
    model = UnModNet(TIERS["tiny"]).eval()
    m = torch.rand(2, 1, 32, 32)
    winding = torch.randint(0, 3, (2, 1, 32, 32))
    edges = model.edge(m)
    plain = rollover_losses(model, m, winding, edges, torch.Generator().manual_seed(5))
    again = rollover_losses(model, m, winding, edges, torch.Generator().manual_seed(5), 0.0)
    assert torch.equal(plain[0], again[0])
    own_loss, own_accuracy = rollover_losses(
        model, m, winding, edges, torch.Generator().manual_seed(5), 1.0, 3
    )
    assert torch.isfinite(own_loss) and 0.0 <= float(own_accuracy) <= 1.0
    assert not torch.equal(own_loss, plain[0])


def test_unmodnet_trains_on_its_own_states(tmp_path: Path) -> None:
    config = TrainConfig(
        family="unmodnet", tier="tiny", stage_steps=(1, 2, 2), crop=32, batch=2,
        runs_dir=tmp_path, own_states=1.0, own_passes=2, log_every=1,
    )  # fmt: skip
    checkpoint = train(config)
    assert load_checkpoint(checkpoint)["step"] == 5


def test_a_deadline_stops_with_a_checkpoint_that_resumes(tmp_path: Path) -> None:
    whole = load_checkpoint(train(tiny_config(tmp_path / "a", (1, 2, 1))))
    cut = load_checkpoint(train(tiny_config(tmp_path / "b", (1, 2, 1)), deadline=0.0))
    assert cut["step"] == 1
    resumed = load_checkpoint(train(tiny_config(tmp_path / "b", (1, 2, 1))))
    assert resumed["step"] == 4
    for key, value in whole["model"].items():
        torch.testing.assert_close(resumed["model"][key], value)


def test_prefetching_workers_train_the_same_model(tmp_path: Path) -> None:
    alone = load_checkpoint(train(tiny_config(tmp_path / "a", (1, 2, 1))))
    config = replace(tiny_config(tmp_path / "b", (1, 2, 1)), workers=2)
    ahead = load_checkpoint(train(config))
    for key, value in alone["model"].items():
        torch.testing.assert_close(ahead["model"][key], value)


def test_bf16_autocast_trains_every_stage(tmp_path: Path) -> None:
    config = replace(tiny_config(tmp_path, (1, 1, 1)), stage_steps=(1, 1, 1, 1), large_crop=32)
    state = load_checkpoint(train(replace(config, precision="bf16")))
    assert state["step"] == 4
    assert all(torch.isfinite(v).all() for v in state["model"].values() if v.is_floating_point())


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"precision": "fp16"}, "precision must be one of"),
        ({"workers": -1}, "workers must be >= 0"),
    ],
)
def test_run_settings_are_checked(tmp_path: Path, change: dict[str, object], message: str) -> None:
    with pytest.raises(ValueError, match=message):
        train(replace(tiny_config(tmp_path, (1, 1, 1)), **change))  # type: ignore[arg-type]


@pytest.mark.skipif(torch.cuda.is_available(), reason="this machine has a CUDA GPU")
def test_a_gpu_run_without_a_gpu_says_so(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="torch sees no CUDA GPU"):
        train(replace(tiny_config(tmp_path, (1, 1, 1)), device="cuda"))


def test_each_resumed_stretch_of_a_run_is_a_segment(tmp_path: Path) -> None:
    train(tiny_config(tmp_path, (1, 1, 0)))
    state = load_checkpoint(train(tiny_config(tmp_path, (1, 2, 1))))
    segments = state["segments"]
    assert [s["steps"] for s in segments] == [[0, 2], [2, 4]]
    assert all(s["device"] == "cpu" and s["precision"] == "fp32" for s in segments)
    assert all(s["hardware"] and s["wall_s"] >= 0.0 for s in segments)
    assert checkpoint_segments(state) == segments


def test_a_checkpoint_from_before_segments_is_one_cpu_segment() -> None:
    old = {"step": 7, "wall_s": 12.34, "config": {"tier": "tiny"}}
    assert checkpoint_segments(old) == [
        {"hardware": "cpu", "device": "cpu", "precision": "fp32", "steps": [0, 7], "wall_s": 12.3}
    ]
    assert checkpoint_segments({**old, "step": 0}) == []
