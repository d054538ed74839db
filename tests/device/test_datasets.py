"""Tests of device/datasets.py: pair folders that never collide, and the per-device bound."""

from __future__ import annotations

import logging
import stat
from pathlib import Path

import pytest

from device.datasets import (
    DatasetLimits,
    device_dir,
    finish_pair,
    new_pair_folder,
    pair_folders,
    prune_pairs,
)


def pairs(root: Path, count: int, size: int = 100) -> list[Path]:
    """``count`` pair folders of cam1, oldest first, each with one file of ``size`` bytes."""
    folders = [new_pair_folder(root, "cam1", sequence=7) for _ in range(count)]
    for folder in folders:
        (folder / "reference.exr").write_bytes(bytes(size))
    return [finish_pair(folder) for folder in folders]


def test_the_same_sequence_gets_a_new_folder_each_time(tmp_path: Path) -> None:
    first, second = pairs(tmp_path, 2)
    assert first != second and first.name.endswith("-0000000007")
    assert sorted([second.name, first.name]) == [first.name, second.name]
    assert first.parent == device_dir(tmp_path, "cam1")
    for folder in (first, first.parent, first.parent.parent):
        assert stat.S_IMODE(folder.stat().st_mode) == 0o700, folder


def test_the_oldest_pairs_beyond_the_count_are_removed_and_logged(
        tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    folders = pairs(tmp_path, 5)
    with caplog.at_level(logging.INFO, logger="device.datasets"):
        removed = prune_pairs(tmp_path, "cam1", DatasetLimits(max_pairs=3))
    assert removed == folders[:2]
    assert sorted(device_dir(tmp_path, "cam1").iterdir()) == folders[2:]
    assert "removed the 2 oldest dataset pairs of cam1" in caplog.text
    assert folders[0].name in caplog.text


def test_the_oldest_pairs_beyond_the_bytes_are_removed(tmp_path: Path) -> None:
    folders = pairs(tmp_path, 4, size=100)
    assert prune_pairs(tmp_path, "cam1", DatasetLimits(max_bytes=250)) == folders[:2]
    assert prune_pairs(tmp_path, "cam1", DatasetLimits(max_bytes=250)) == []


def test_the_newest_pair_is_kept_even_when_it_alone_is_too_large(tmp_path: Path) -> None:
    folders = pairs(tmp_path, 2, size=1000)
    assert prune_pairs(tmp_path, "cam1", DatasetLimits(max_bytes=10)) == folders[:1]
    assert folders[1].is_dir()


def test_a_pair_being_written_is_hidden_and_never_counted_or_pruned(tmp_path: Path) -> None:
    folders = pairs(tmp_path, 2)
    unfinished = new_pair_folder(tmp_path, "cam1", sequence=8)
    (unfinished / "wrapped.png").write_bytes(bytes(10))
    assert unfinished.name.startswith(".") and unfinished.parent == folders[0].parent
    assert pair_folders(tmp_path, "cam1") == folders
    assert prune_pairs(tmp_path, "cam1", DatasetLimits(max_pairs=2)) == []
    assert unfinished.is_dir()
    finished = finish_pair(unfinished)
    assert finished.name == unfinished.name[1:] and (finished / "wrapped.png").is_file()
    assert pair_folders(tmp_path, "cam1") == [*folders, finished]
