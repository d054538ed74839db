"""Tests of models/decoders/model_install.py: installed model files checked against
their cards, for the API's readiness."""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import pytest

from models.decoders import learned, model_install
from models.decoders.model_install import broken_models, file_matches

CARD = "mantissanet-tiny-modulo"


def install_one(folder: Path) -> Path:
    """A model folder holding one real card and its ONNX file; the file's path."""
    folder.mkdir()
    shutil.copy(learned.ONNX_DIR / f"{CARD}.json", folder)
    return Path(shutil.copy(learned.ONNX_DIR / f"{CARD}.onnx", folder))


def test_the_shipped_models_are_their_cards() -> None:
    assert broken_models() == []


def test_a_file_cut_short_is_named_without_its_folder_then_cleared_once_restored(
    tmp_path: Path,
) -> None:
    onnx = install_one(tmp_path / "onnx")
    assert broken_models(onnx.parent) == []
    whole = onnx.read_bytes()
    onnx.write_bytes(whole[: len(whole) // 2])
    [line] = broken_models(onnx.parent)
    assert f"{CARD}.onnx" in line and "'mantissanet-tiny'" in line and "modulo" in line
    assert str(tmp_path) not in line and "restore it" in line
    onnx.write_bytes(whole)
    assert broken_models(onnx.parent) == []


def test_a_file_replaced_in_place_with_the_same_size_and_time_is_seen_by_its_hash(
    tmp_path: Path,
) -> None:
    """The cache is keyed by the file's stat (:func:`stat_key`): a rewrite is seen by
    its hash once the stat differs (a new mtime here)."""
    onnx = install_one(tmp_path / "onnx")
    card_sha = learned.read_card(onnx.with_suffix(".json"))["sha256"]
    assert file_matches(onnx, card_sha)
    data = bytearray(onnx.read_bytes())
    data[-1] ^= 0xFF
    onnx.write_bytes(bytes(data))
    stat = onnx.stat()
    os.utime(onnx, ns=(stat.st_atime_ns, stat.st_mtime_ns + 1_000_000))
    assert not file_matches(onnx, card_sha)


def test_a_checked_file_is_hashed_again_once_its_mode_changes_and_only_then(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A poll hashes an unchanged file once; a chmod, which keeps the size and mtime,
    made the cached answer outlive the file becoming unreadable."""
    onnx = install_one(tmp_path / "onnx")
    card_sha = learned.read_card(onnx.with_suffix(".json"))["sha256"]
    hashed: list[Path] = []

    def counting(path: Path) -> str:
        hashed.append(path)
        return learned.sha256_of(path)

    monkeypatch.setattr(model_install, "sha256_of", counting)
    assert file_matches(onnx, card_sha) and file_matches(onnx, card_sha)
    assert hashed == [onnx]
    onnx.chmod(0o400)
    assert file_matches(onnx, card_sha) and file_matches(onnx, card_sha)
    assert hashed == [onnx, onnx]


@pytest.mark.skipif(os.geteuid() == 0, reason="root reads a file whatever its mode")
def test_a_file_made_unreadable_after_it_was_checked_is_named(tmp_path: Path) -> None:
    """``chmod 000`` keeps a file's size and mtime: readiness kept the cached "intact"
    and said ready while loading the model failed."""
    onnx = install_one(tmp_path / "onnx")
    assert broken_models(onnx.parent) == []
    onnx.chmod(0)
    try:
        [line] = broken_models(onnx.parent)
    finally:
        onnx.chmod(0o644)
    assert f"{CARD}.onnx" in line and "cannot be read" in line and str(tmp_path) not in line
    assert broken_models(onnx.parent) == []


def test_a_file_removed_after_it_was_checked_does_not_match(tmp_path: Path) -> None:
    onnx = install_one(tmp_path / "onnx")
    card_sha = learned.read_card(onnx.with_suffix(".json"))["sha256"]
    assert file_matches(onnx, card_sha)
    onnx.unlink()
    assert not file_matches(onnx, card_sha)


def test_the_served_folder_is_read_when_called(tmp_path: Path,
                                              monkeypatch: pytest.MonkeyPatch) -> None:
    onnx = install_one(tmp_path / "onnx")
    onnx.write_bytes(b"not a model")
    monkeypatch.setattr(learned, "ONNX_DIR", onnx.parent)
    assert len(model_install.broken_models()) == 1


def test_a_directory_in_place_of_a_model_file_is_named_not_raised(tmp_path: Path) -> None:
    """A directory named like the model file made the readiness check raise
    IsADirectoryError (a 500 from /health/ready) instead of naming the file."""
    onnx = install_one(tmp_path / "onnx")
    onnx.unlink()
    onnx.mkdir()
    [line] = broken_models(onnx.parent)
    assert f"{CARD}.onnx" in line and "cannot be read" in line and str(tmp_path) not in line


def test_a_file_removed_while_its_card_stays_is_named_missing(tmp_path: Path) -> None:
    """The API and workers list a decoder from the cards read at start, so a model file
    removed since makes its jobs fail as model_unavailable; readiness skipped its card
    (it only looked at cards whose file exists) and said the decoders were ready."""
    onnx = install_one(tmp_path / "onnx")
    assert broken_models(onnx.parent) == []
    onnx.unlink()
    [line] = broken_models(onnx.parent)
    assert f"{CARD}.onnx" in line and "is missing" in line and "restore it" in line
    assert str(tmp_path) not in line
