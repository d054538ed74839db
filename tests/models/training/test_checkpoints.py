"""Tests of models/training/checkpoints.py: atomic writes and run segments."""

from __future__ import annotations

from pathlib import Path

import torch

from models.training.checkpoints import (
    checkpoint_segments,
    hardware_name,
    load_checkpoint,
    save_checkpoint,
)


def test_a_checkpoint_from_before_segments_is_one_cpu_segment() -> None:
    old = {"step": 7, "wall_s": 12.34, "config": {"tier": "tiny"}}
    assert checkpoint_segments(old) == [
        {"hardware": "cpu", "device": "cpu", "precision": "fp32", "steps": [0, 7], "wall_s": 12.3}
    ]
    assert checkpoint_segments({**old, "step": 0}) == []


def test_a_checkpoint_is_written_whole_and_read_back(tmp_path: Path) -> None:
    path = tmp_path / "checkpoint.pt"
    save_checkpoint(path, {"step": 3, "weights": torch.arange(4.0)})
    state = load_checkpoint(path)
    assert state["step"] == 3 and torch.equal(state["weights"], torch.arange(4.0))
    assert not list(tmp_path.glob("*.tmp"))


def test_the_cpu_has_a_name() -> None:
    assert hardware_name(torch.device("cpu"))
