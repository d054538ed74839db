"""Tests of worker/private_dirs.py: owner-only folders, created or narrowed."""

from __future__ import annotations

import stat
from pathlib import Path

from worker.private_dirs import make_private_dirs, private_dir


def mode(path: Path) -> int:
    return stat.S_IMODE(path.stat().st_mode)


def test_missing_folders_are_created_owner_only_and_existing_ones_kept(tmp_path: Path) -> None:
    shared = tmp_path / "shared"
    shared.mkdir(mode=0o755)
    shared.chmod(0o755)
    make_private_dirs(shared / "data" / "results")
    assert mode(shared) == 0o755
    assert mode(shared / "data") == mode(shared / "data" / "results") == 0o700


def test_private_dir_narrows_a_folder_an_older_version_made_readable(tmp_path: Path) -> None:
    tmp_path.chmod(0o755)
    old = tmp_path / "results"
    old.mkdir()
    old.chmod(0o755)
    assert private_dir(old) == old and mode(old) == 0o700
    assert mode(tmp_path) == 0o755
