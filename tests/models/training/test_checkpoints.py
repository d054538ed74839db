"""Tests of models/training/checkpoints.py: atomic writes and run segments."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest
import torch

from models.errors import InvalidInputError
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


def checkpoint_state(weights: torch.Tensor) -> dict[str, Any]:
    """A checkpoint's state at step 3 with ``weights`` for its model."""
    return {"model": {"weights": weights}, "optimizer": {}, "step": 3, "wall_s": 1.0,
            "config": {"tier": "tiny"}}  # fmt: skip


def test_a_checkpoint_is_written_whole_and_read_back(tmp_path: Path) -> None:
    path = tmp_path / "checkpoint.pt"
    save_checkpoint(path, checkpoint_state(torch.arange(4.0)))
    state = load_checkpoint(path)
    assert state["step"] == 3 and torch.equal(state["model"]["weights"], torch.arange(4.0))
    assert not list(tmp_path.glob("*.tmp"))


def test_the_cpu_has_a_name() -> None:
    assert hardware_name(torch.device("cpu"))


@pytest.mark.parametrize("damage", ["empty", "cut-short", "garbage"])
def test_an_unreadable_checkpoint_is_one_clear_error(tmp_path: Path, damage: str) -> None:
    path = tmp_path / "checkpoint.pt"
    save_checkpoint(path, checkpoint_state(torch.arange(1000.0)))
    whole = path.read_bytes()
    damaged = {"empty": b"", "cut-short": whole[: len(whole) // 2], "garbage": b"x" * 64}
    path.write_bytes(damaged[damage])
    with pytest.raises(InvalidInputError, match="not a readable checkpoint") as caught:
        load_checkpoint(path, resuming=True)
    assert str(path) in caught.value.message and "delete the run folder" in caught.value.message
    with pytest.raises(InvalidInputError, match="not a readable checkpoint") as caught:
        load_checkpoint(path)  # an export's or init_from's: the user's file, not a run's
    assert "delete" not in caught.value.message and "training wrote" in caught.value.message


def test_any_cut_or_flipped_byte_is_the_clear_error_or_loads(tmp_path: Path) -> None:
    """A file cut short can raise OSError (EINVAL), a flipped byte a UnicodeDecodeError:
    each the same clear error as above (they were a bare 'Invalid argument' and a
    traceback), or the file still loads."""
    path = tmp_path / "checkpoint.pt"
    save_checkpoint(path, checkpoint_state(torch.arange(1000.0)))
    whole = path.read_bytes()
    cuts = [whole[:cut] for cut in range(0, len(whole), 97)]
    flips = []
    for at in range(0, len(whole), 53):
        flipped = bytearray(whole)
        flipped[at] ^= 0xFF
        flips.append(bytes(flipped))
    refused = []
    for data in cuts + flips:
        path.write_bytes(data)
        try:
            load_checkpoint(path)
        except InvalidInputError as exc:
            assert "not a readable checkpoint" in exc.message
            refused.append(data)
    assert all(cut in refused for cut in cuts) and any(flip in refused for flip in flips)


def test_a_state_dict_alone_is_refused_naming_what_it_lacks(tmp_path: Path) -> None:
    """A model's weights saved alone loaded, then failed with a bare KeyError: 'config'."""
    path = tmp_path / "weights.pt"
    torch.save({"head.weight": torch.zeros(2)}, path)
    with pytest.raises(InvalidInputError, match="lacks model, optimizer, step, wall_s, config"):
        load_checkpoint(path)
    stepless = checkpoint_state(torch.zeros(2))
    del stepless["step"]
    torch.save(stepless, path)
    with pytest.raises(InvalidInputError, match=f"{path} .*lacks step:") as caught:
        load_checkpoint(path, resuming=True)
    assert "delete the run folder" in caught.value.message


def test_a_folder_is_not_called_a_damaged_checkpoint(tmp_path: Path) -> None:
    """A folder was 'not a readable checkpoint ([Errno 21] Is a directory: ...): it is
    empty, cut short or corrupt'; it is the OSError the CLI words as 'is a folder'."""
    with pytest.raises(IsADirectoryError):
        load_checkpoint(tmp_path)
