"""Tests of models/training/train.py: a tiny seeded run, its log, and resuming."""

from __future__ import annotations

import json
import os
import signal
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import Any

import pytest
import torch

from models.errors import InvalidInputError
from models.training.checkpoints import checkpoint_segments, load_checkpoint
from models.training.config import TrainConfig
from models.training.losses import HEAD_OUTPUTS
from models.training.run_control import Stopped, run_lock
from models.training.train import TrainingDivergedError, divergence_advice, train


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


class Crash(Exception):
    """What :func:`crash_at` raises: the process died there."""


def crash_at(step: int) -> Callable[[dict[str, Any]], None]:
    """A report that raises at ``step``'s log record (after the step, before its
    checkpoint), as a process killed there would stop."""

    def report(record: dict[str, Any]) -> None:
        if record["step"] == step:
            raise Crash(step)

    return report


def interrupted(config: TrainConfig, step: int) -> None:
    """Train ``config`` until it crashes at ``step`` (its last checkpoint before)."""
    with pytest.raises(Crash):
        train(config, crash_at(step))


def test_resumed_run_equals_an_uninterrupted_one(tmp_path: Path) -> None:
    whole = load_checkpoint(train(tiny_config(tmp_path / "a", (1, 2, 1))))
    interrupted(tiny_config(tmp_path / "b", (1, 2, 1)), 3)
    cut = load_checkpoint(tmp_path / "b" / "mantissanet-tiny-mantissa" / "checkpoint.pt")
    assert cut["step"] == 2
    resumed = load_checkpoint(train(tiny_config(tmp_path / "b", (1, 2, 1))))
    assert resumed["step"] == whole["step"] == 4
    for key, value in whole["model"].items():
        torch.testing.assert_close(resumed["model"][key], value)


def test_unknown_loss_is_refused(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="loss must be one of"):
        train(TrainConfig(loss="l1", runs_dir=tmp_path))


@pytest.mark.parametrize("weight", [-1.0, float("inf"), float("nan")])
def test_a_risk_weight_not_finite_and_positive_is_refused(tmp_path: Path, weight: float) -> None:
    """An infinite weight trained NaN weights and exported them."""
    with pytest.raises(ValueError, match="risk_weight must be finite and >= 0"):
        train(TrainConfig(loss="ce-risk", risk_weight=weight, runs_dir=tmp_path))


def test_a_run_whose_loss_is_not_finite_stops_with_the_reason(tmp_path: Path) -> None:
    """A risk weight of 1e300 makes the small net's loss infinite at its second step:
    the run stops there, saving nothing past it (it trained on to NaN weights)."""
    config = TrainConfig(tier="small", loss="ce-risk", risk_weight=1e300,
                         stage_steps=(1, 1, 1), crop=32, batch=2, runs_dir=tmp_path)  # fmt: skip
    diverged = "diverged at step 2: its loss is inf"
    with pytest.raises(TrainingDivergedError, match=diverged) as caught:
        train(config)
    assert not (config.run_dir / "checkpoint.pt").exists()
    assert "a lower --risk-weight (now 1e+300) or another --seed" in caught.value.message


def test_the_divergence_advice_names_only_options_mcam_train_run_has() -> None:
    """It said "a lower learning rate", which no option sets."""
    advice = divergence_advice(TrainConfig(precision="bf16"))
    assert "--precision fp32 or another --seed" in advice and "--risk-weight" not in advice
    assert "learning rates are fixed per stage" in advice


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


def test_a_run_may_not_start_from_an_unfinished_one(tmp_path: Path) -> None:
    train(tiny_config(tmp_path, (1, 1, 1)), deadline=0.0)  # stops after its first step
    config = TrainConfig(
        tier="tiny", stage_steps=(0, 0, 0, 0), crop=32, batch=2, runs_dir=tmp_path,
        max_read_noise=0.02, init_from="mantissanet-tiny-mantissa",
    )  # fmt: skip
    with pytest.raises(InvalidInputError, match="stopped at step 1 of 3: train it to the end"):
        train(config)


@pytest.mark.parametrize(
    ("change", "target"),
    [({"tier": "small"}, "mantissanet small net with 17"), ({"family": "unmodnet"}, "unmodnet"),
     ({"loss": "mse"}, "mantissanet tiny net with 1 outputs")],
)
def test_a_run_may_not_start_from_another_nets_weights(
    tmp_path: Path, change: dict[str, str], target: str
) -> None:
    """Another tier, family or head failed in load_state_dict with torch's 'Missing
    key(s) in state_dict' or 'size mismatch' traceback."""
    train(tiny_config(tmp_path, (1, 1, 1)))
    config = replace(
        tiny_config(tmp_path, (0, 0, 1)), init_from="mantissanet-tiny-mantissa", **change
    )
    with pytest.raises(InvalidInputError, match=f"trains a {target}.*the weights do not fit"):
        train(config)


def test_a_missing_initial_run_is_named_in_the_error(tmp_path: Path) -> None:
    config = TrainConfig(tier="tiny", stage_steps=(0, 0, 0, 1), runs_dir=tmp_path,
                         init_from="mantissanet-nothing")  # fmt: skip
    with pytest.raises(FileNotFoundError, match="train mantissanet-nothing first"):
        train(config)


def test_unmodnet_refuses_a_loss_it_would_ignore(tmp_path: Path) -> None:
    with pytest.raises(InvalidInputError, match="unmodnet learns its rollover masks"):
        train(TrainConfig(family="unmodnet", loss="jumps", runs_dir=tmp_path))
    assert not any(tmp_path.iterdir())


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
    interrupted(tiny_config(tmp_path, (1, 2, 1)), 3)
    state = load_checkpoint(train(tiny_config(tmp_path, (1, 2, 1))))
    segments = state["segments"]
    assert [s["steps"] for s in segments] == [[0, 2], [2, 4]]
    assert all(s["device"] == "cpu" and s["precision"] == "fp32" for s in segments)
    assert all(s["hardware"] and s["wall_s"] >= 0.0 for s in segments)
    assert checkpoint_segments(state) == segments




@pytest.mark.parametrize(
    ("change", "named"),
    [
        ({"seed": 4}, "seed 3 (now 4)"),
        ({"stage_steps": (1, 2, 2, 1)}, "stage_steps (1, 1, 0) (now (1, 2, 2, 1))"),
        ({"crop": 48, "batch": 1}, "crop 32 (now 48), batch 2 (now 1)"),
        ({"large_crop": 64}, "large_crop 128 (now 64)"),
        ({"max_read_noise": 0.01}, "max_read_noise 0.0 (now 0.01)"),
    ],
)
def test_a_checkpoint_of_other_settings_is_neither_resumed_nor_returned(
    tmp_path: Path, change: dict[str, Any], named: str
) -> None:
    """A finished run keeps its settings: another seed, stages, crop, ... on its folder
    (renamed, where the change renames the run) is refused, naming each difference, and
    the checkpoint stays as it was."""
    first = replace(tiny_config(tmp_path, (1, 1, 0)), seed=3)
    train(first)
    changed = replace(first, **change)
    first.run_dir.rename(tmp_path / "moved")
    (tmp_path / "moved").rename(changed.run_dir)
    checkpoint = changed.run_dir / "checkpoint.pt"
    before = checkpoint.read_bytes()
    with pytest.raises(InvalidInputError, match="trained with other settings") as caught:
        train(changed)
    assert named in caught.value.message
    assert "another --runs-dir or --label" in caught.value.message
    assert checkpoint.read_bytes() == before


def test_a_resume_may_change_where_and_how_the_steps_run(tmp_path: Path) -> None:
    config = tiny_config(tmp_path, (1, 2, 1))
    interrupted(config, 3)
    faster = replace(config, threads=2, workers=1, checkpoint_every=1, log_every=2)
    assert load_checkpoint(train(faster))["step"] == 4


def test_a_locked_run_folder_is_refused_naming_the_holder(tmp_path: Path) -> None:
    config = tiny_config(tmp_path, (1, 1, 1))
    with run_lock(config.run_dir):
        with pytest.raises(InvalidInputError, match=f"being trained by process {os.getpid()}"):
            train(config)
    assert not (config.run_dir / "checkpoint.pt").exists()
    assert load_checkpoint(train(config))["step"] == 3


def test_a_resumed_run_logs_each_step_once(tmp_path: Path) -> None:
    """The steps after the last checkpoint, logged before a crash, are made again on
    resume: the log keeps one record per step (a line cut short by the crash dropped)."""
    config = tiny_config(tmp_path, (1, 2, 2))
    interrupted(config, 3)
    log = config.run_dir / "log.jsonl"
    with log.open("a") as file:
        file.write('{"step": 4, "sta')
    train(config)
    steps = [json.loads(line)["step"] for line in log.read_text().splitlines()]
    assert steps == [1, 2, 3, 4, 5]


def signal_at(step: int, signum: int) -> Callable[[dict[str, Any]], None]:
    """A report that sends this process ``signum`` at ``step``'s log record."""

    def report(record: dict[str, Any]) -> None:
        if record["step"] == step:
            os.kill(os.getpid(), signum)

    return report


@pytest.mark.parametrize(
    ("signum", "workers"), [(signal.SIGTERM, 0), (signal.SIGINT, 0), (signal.SIGINT, 1)]
)
def test_a_signal_stops_after_the_step_with_a_checkpoint_that_resumes(
    tmp_path: Path, signum: int, workers: int
) -> None:
    whole = load_checkpoint(train(tiny_config(tmp_path / "a", (1, 2, 2))))
    config = replace(tiny_config(tmp_path / "b", (1, 2, 2)), workers=workers)
    handlers = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}
    with pytest.raises(Stopped, match="resume from step 3") as caught:
        train(config, signal_at(3, signum))
    assert (caught.value.signum, caught.value.step, caught.value.total) == (signum, 3, 5)
    assert load_checkpoint(caught.value.checkpoint)["step"] == 3
    assert {s: signal.getsignal(s) for s in handlers} == handlers  # restored (SIG_IGN under nohup)
    resumed = load_checkpoint(train(config))
    assert resumed["step"] == 5
    for key, value in whole["model"].items():
        torch.testing.assert_close(resumed["model"][key], value)


def test_a_checkpoint_whose_weights_do_not_fit_its_net_is_one_clear_error(
    tmp_path: Path,
) -> None:
    """A checkpoint of a version whose nets differed (here: one layer's weights gone)
    failed to resume in load_state_dict with PyTorch's 'Missing key(s)' traceback."""
    config = tiny_config(tmp_path, (1, 1, 1))
    checkpoint = train(config)
    state = load_checkpoint(checkpoint)
    layer = next(iter(state["model"]))
    del state["model"][layer]
    torch.save(state, checkpoint)
    expected = f"weights do not fit .*Missing key.*{layer}"
    with pytest.raises(InvalidInputError, match=expected) as caught:
        train(config)
    assert str(checkpoint) in caught.value.message
    assert "delete the run folder" in caught.value.message
