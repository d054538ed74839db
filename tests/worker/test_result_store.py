"""ResultStore: atomic durable writes, keys that can never escape the root, retention."""

from __future__ import annotations

import os
import stat
import threading
import time
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from worker.result_store import (
    InvalidKeyError,
    ResultNotFoundError,
    ResultStore,
    validate_key,
)


@pytest.fixture
def store(tmp_path: Path) -> ResultStore:
    return ResultStore(tmp_path / "results", retention_s=60.0)


def test_write_read_roundtrip(store: ResultStore) -> None:
    path = store.write("jobs/abc/result.exr", b"\x00\x01payload")
    assert path == store.root / "jobs" / "abc" / "result.exr"
    assert store.exists("jobs/abc/result.exr")
    assert store.read("jobs/abc/result.exr") == b"\x00\x01payload"


def test_write_replaces_and_leaves_no_temp_files(store: ResultStore) -> None:
    store.write("a/b.bin", b"first")
    store.write("a/b.bin", b"second")
    assert store.read("a/b.bin") == b"second"
    assert sorted(p.name for p in (store.root / "a").iterdir()) == ["b.bin"]


def test_results_are_readable_by_their_owner_only(tmp_path: Path) -> None:
    root = tmp_path / "data" / "results"
    store = ResultStore(root, retention_s=60.0)
    path = store.write("jobs/abc/result.exr", b"pixels")
    assert stat.S_IMODE(path.stat().st_mode) == 0o600
    for folder in (root.parent, root, root / "jobs", root / "jobs" / "abc"):
        assert stat.S_IMODE(folder.stat().st_mode) == 0o700, folder


def test_an_existing_readable_store_folder_is_narrowed(tmp_path: Path) -> None:
    root = tmp_path / "results"
    root.mkdir()
    root.chmod(0o755)
    ResultStore(root, retention_s=60.0)
    assert stat.S_IMODE(root.stat().st_mode) == 0o700


def test_read_missing_is_not_found(store: ResultStore) -> None:
    with pytest.raises(ResultNotFoundError) as info:
        store.read("jobs/none/result.exr")
    assert info.value.http_status == 404
    assert not store.exists("jobs/none/result.exr")


@pytest.mark.parametrize(
    "key",
    [
        "",
        "/etc/passwd",
        "../x",
        "a/../../x",
        "a//b",
        "a/./b",
        "a\\b",
        "a b",
        "a/b/",
        "~",
        "x.tmp",
        "é",
        "a\x00b",
        "a" * 600,
    ],
)
def test_unsafe_keys_rejected(store: ResultStore, key: str) -> None:
    with pytest.raises(InvalidKeyError):
        store.path(key)
    with pytest.raises(InvalidKeyError):
        store.write(key, b"x")


def test_a_long_unsafe_key_is_echoed_cut_short() -> None:
    with pytest.raises(InvalidKeyError, match=r"\(and 39920 more characters\): use a relative"):
        validate_key("../" * 13_333 + "x")


#: Characters of keys: allowed ones, dots and slashes among them to make
#: '.' and '..' components (over any text, only 13 in 200 keys passed validate_key).
KEY_ALPHABET = "a0_-./"


@settings(max_examples=200, deadline=None)
@given(st.text(KEY_ALPHABET, min_size=1, max_size=40))
def test_any_accepted_key_stays_inside_root(key: str) -> None:
    root = Path("/srv/results")
    try:
        validate_key(key)
    except InvalidKeyError:
        return
    resolved = (root / key).resolve()
    assert resolved.is_relative_to(root) and resolved != root


def test_purge_expired_removes_old_files_and_empty_folders(store: ResultStore) -> None:
    old = store.write("jobs/old/result.exr", b"old")
    store.write("jobs/new/result.exr", b"new")
    past = time.time() - 3600
    os.utime(old, (past, past))
    assert store.purge_expired() == 1
    assert not store.exists("jobs/old/result.exr")
    assert not (store.root / "jobs" / "old").exists()
    assert store.read("jobs/new/result.exr") == b"new"
    assert store.purge_expired(now_s=time.time() + 120) == 1
    assert list(store.root.iterdir()) == []


def test_a_write_that_may_not_replace_keeps_the_first_file(store: ResultStore) -> None:
    store.write("devices/cam/0.exr", b"first", replace=False)
    store.write("devices/cam/0.exr", b"second", replace=False)
    assert store.read("devices/cam/0.exr") == b"first"
    assert store.keys() == ["devices/cam/0.exr"]
    assert [p.name for p in (store.root / "devices" / "cam").iterdir()] == ["0.exr"]
    store.write("devices/cam/0.exr", b"third")
    assert store.read("devices/cam/0.exr") == b"third"


def test_a_stopped_purge_leaves_the_rest_for_the_next(store: ResultStore) -> None:
    """A purge asked to stop (the worker is shutting down) ends its walk; what it did
    not reach is purged next time."""
    old = store.write("jobs/old/result.exr", b"old")
    past = time.time() - 3600
    os.utime(old, (past, past))
    stop = threading.Event()
    stop.set()
    assert store.purge_expired(stop=stop) == 0
    assert store.exists("jobs/old/result.exr")
    assert store.purge_expired() == 1


def test_purge_removes_temp_files_of_dead_writers(store: ResultStore) -> None:
    store.write("jobs/a/result.exr", b"ok")
    leftover = store.root / "jobs" / "a" / ".result.exr.123.456.tmp"
    leftover.write_bytes(b"half")
    assert store.keys() == ["jobs/a/result.exr"]
    assert store.purge_expired() == 0
    past = time.time() - 2 * 3600
    os.utime(leftover, (past, past))
    assert store.purge_expired() == 1
    assert store.keys("jobs") == ["jobs/a/result.exr"]


def test_retention_must_be_positive(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="retention_s"):
        ResultStore(tmp_path, retention_s=0)


def test_delete(store: ResultStore) -> None:
    store.write("k", b"v")
    assert store.delete("k") is True
    assert store.delete("k") is False


def test_delete_folder_removes_its_files_temp_files_and_folders_only(
    store: ResultStore,
) -> None:
    """A cancelled job's folder goes whole (a writer's temp file too); its neighbours stay."""
    store.write("jobs/a/result.exr", b"a")
    store.write("jobs/a/sub/winding.npy", b"w")
    (store.root / "jobs" / "a" / ".codes.npy.1.2.tmp").write_bytes(b"t")
    store.write("jobs/ab/result.exr", b"kept")
    assert store.delete_folder("jobs/a") == 3
    assert not (store.root / "jobs" / "a").exists()
    assert store.keys() == ["jobs/ab/result.exr"]
    assert store.delete_folder("jobs/a") == 0
    with pytest.raises(InvalidKeyError):
        store.delete_folder("jobs/../..")


Event = tuple[str | int, ...]


def record_durability_calls(monkeypatch: pytest.MonkeyPatch) -> list[Event]:
    """Spy on ``os.fsync``, ``os.replace`` and ``os.link`` (each still runs): a list of
    ``("fsync file", inode, bytes in the file)``, ``("fsync dir", inode)`` and
    ``("replace" | "link", inode of the source, destination)``, in call order."""
    events: list[Event] = []
    real_fsync, real_replace, real_link = os.fsync, os.replace, os.link

    def fsync(fd: int) -> None:
        info = os.fstat(fd)
        if stat.S_ISDIR(info.st_mode):
            events.append(("fsync dir", info.st_ino))
        else:
            events.append(("fsync file", info.st_ino, info.st_size))
        real_fsync(fd)

    def replace(src: Path, dst: Path) -> None:
        events.append(("replace", os.stat(src).st_ino, str(dst)))
        real_replace(src, dst)

    def link(src: Path, dst: Path) -> None:
        events.append(("link", os.stat(src).st_ino, str(dst)))
        real_link(src, dst)

    monkeypatch.setattr(os, "fsync", fsync)
    monkeypatch.setattr(os, "replace", replace)
    monkeypatch.setattr(os, "link", link)
    return events


@pytest.mark.parametrize(("replace", "naming"), [(True, "replace"), (False, "link")])
def test_a_write_syncs_its_file_before_naming_it_and_the_folder_after(
    store: ResultStore, monkeypatch: pytest.MonkeyPatch, replace: bool, naming: str
) -> None:
    """A crash can leave the old result or the new one, never a named empty or partial
    file: the data is flushed and fsynced, then the file named, then its folder fsynced
    (which makes the name itself durable)."""
    events = record_durability_calls(monkeypatch)
    data = b"\x00payload" * 100
    final = store.write("jobs/a/result.exr", data, replace=replace)
    file, folder = final.stat().st_ino, final.parent.stat().st_ino
    assert events == [
        ("fsync file", file, len(data)),
        (naming, file, str(final)),
        ("fsync dir", folder),
    ]
