"""Durable result files on disk, addressed by validated keys, with a retention time.

Usage::

    store = ResultStore(Path("data/results"), retention_s=7 * 86400)
    path = store.write("jobs/0123abcd.../result.exr", exr_bytes)  # atomic + fsynced
    store.exists(key); store.read(key); store.existing_path(key)
    store.purge_expired()  # deletes files older than retention_s, returns how many
    store.delete_folder("jobs/0123abcd...")  # a cancelled job's files, temp files too

Keys are relative paths of letters, digits and ``_ . / -`` only: no ``..``
component, no absolute path, no empty component. Anything else raises
:class:`InvalidKeyError` before the filesystem is touched, so ids from requests
can never escape the store. Folders are created owner-only (0700) and files 0600:
results are users' images.
"""

from __future__ import annotations

import os
import re
import threading
import time
from collections.abc import Callable, Collection
from pathlib import Path
from typing import BinaryIO

from models.errors import McamError, echo
from worker.private_dirs import PRIVATE_FILE_MODE, make_private_dirs, private_dir

#: Sub-folder of the data dir that holds the result store (API and workers share it).
RESULTS_DIR = "results"
_KEY = re.compile(r"^[A-Za-z0-9_.\-]+(/[A-Za-z0-9_.\-]+)*$")
_TMP_SUFFIX = ".tmp"
#: A temp file this old (s) belongs to a writer that died mid-write.
TMP_MAX_AGE_S = 3600.0


class InvalidKeyError(McamError):
    """A result key is not a safe relative path."""

    code = "invalid_key"
    http_status = 404


class ResultNotFoundError(McamError):
    """No result stored under that key (never written, or purged by retention)."""

    code = "not_found"
    http_status = 404


def _not_found(key: str) -> ResultNotFoundError:
    return ResultNotFoundError(f"no result {key!r} (never written or expired)")


def validate_key(key: str) -> str:
    """Return ``key`` if it is a safe relative path, else raise :class:`InvalidKeyError`."""
    if (
        not isinstance(key, str)
        or len(key) > 512
        or not _KEY.fullmatch(key)
        or any(part in (".", "..") for part in key.split("/"))
        or key.endswith(_TMP_SUFFIX)
    ):
        raise InvalidKeyError(
            f"invalid result key {echo(key)}: use a relative path of letters, digits and '_.-/' "
            "without '..' components"
        )
    return key


def _fsync_dir(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY | os.O_DIRECTORY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _link_unless_present(tmp: Path, final: Path) -> None:
    """Give ``tmp``'s file the name ``final`` unless that name exists (atomic), then drop
    the temp name."""
    try:
        os.link(tmp, final)
    except FileExistsError:
        pass
    tmp.unlink()


class ResultStore:
    """Files under ``root``; ``write`` is atomic (temp file, fsync, rename, fsync dir)."""

    def __init__(self, root: Path, retention_s: float) -> None:
        if retention_s <= 0:
            raise McamError(f"retention_s must be positive, got {retention_s}")
        self.root = Path(root).resolve()
        self.retention_s = retention_s
        private_dir(self.root)

    def path(self, key: str) -> Path:
        """The file that holds ``key`` (it may not exist)."""
        return self.root / validate_key(key)

    def exists(self, key: str) -> bool:
        """True when a result is stored under ``key``."""
        return self.path(key).is_file()

    def existing_path(self, key: str) -> Path:
        """The file that holds ``key``; :class:`ResultNotFoundError` if there is none."""
        path = self.path(key)
        if not path.is_file():
            raise _not_found(key)
        return path

    def read(self, key: str) -> bytes:
        """The bytes stored under ``key``; :class:`ResultNotFoundError` if there are none."""
        try:
            return self.path(key).read_bytes()
        except FileNotFoundError:
            raise _not_found(key) from None

    def open(self, key: str) -> BinaryIO:
        """The file under ``key`` opened for reading (:class:`ResultNotFoundError` if there
        is none): it stays readable to the end though a purge removes it meanwhile."""
        try:
            return self.path(key).open("rb")
        except FileNotFoundError:
            raise _not_found(key) from None

    def write(self, key: str, data: bytes, *, replace: bool = True) -> Path:
        """Store ``data`` under ``key`` durably; an existing result is replaced atomically,
        or, with ``replace=False``, kept (the first complete file under a key wins)."""
        final = self.path(key)
        make_private_dirs(final.parent)
        tmp = final.with_name(f".{final.name}.{os.getpid()}.{time.monotonic_ns()}{_TMP_SUFFIX}")
        try:
            fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, PRIVATE_FILE_MODE)
            with os.fdopen(fd, "wb") as handle:
                handle.write(data)
                handle.flush()
                os.fsync(handle.fileno())
            if replace:
                os.replace(tmp, final)
            else:
                _link_unless_present(tmp, final)
        except BaseException:
            tmp.unlink(missing_ok=True)
            raise
        _fsync_dir(final.parent)
        return final

    def keys(self, prefix: str = "") -> list[str]:
        """Every stored key under folder ``prefix`` (sorted; temp files excluded)."""
        base = self.path(prefix) if prefix else self.root
        return sorted(
            str(path.relative_to(self.root))
            for path in base.rglob("*")
            if path.is_file() and not path.name.endswith(_TMP_SUFFIX)
        )

    def delete(self, key: str) -> bool:
        """Remove the result under ``key``; returns whether there was one."""
        try:
            self.path(key).unlink()
            return True
        except FileNotFoundError:
            return False

    def delete_folder(self, prefix: str) -> int:
        """Remove folder ``prefix`` whole: its files (a writer's temp files too) and its
        folders. Returns how many files; 0 when there is no such folder."""
        return self._sweep(self.path(prefix), lambda _file: True)

    def purge_expired(
        self, now_s: float | None = None, stop: threading.Event | None = None,
        keep: Collection[str] = (),
    ) -> int:
        """Delete results older than the retention time, and temp files a writer left
        when it died (older than an hour); empty folders go too. Returns how many files.
        The results in the folders ``keep`` names (keys) stay, however old.

        A store of a week of 30 frames/s streams holds millions of files and takes
        minutes to walk (about 6 us a file here): run it off any loop with deadlines, and
        set ``stop`` to end the walk early (the rest waits for the next purge)."""
        now = time.time() if now_s is None else now_s
        cutoff = now - self.retention_s
        tmp_cutoff = now - min(self.retention_s, TMP_MAX_AGE_S)
        kept = {self.path(folder) for folder in keep}

        def expired(file: Path) -> bool:
            if file.parent in kept:
                return False
            limit = tmp_cutoff if file.name.endswith(_TMP_SUFFIX) else cutoff
            return file.stat().st_mtime < limit

        return self._sweep(self.root, expired, stop)

    def _sweep(
        self, base: Path, remove: Callable[[Path], bool], stop: threading.Event | None = None
    ) -> int:
        """Delete the files under ``base`` that ``remove`` picks, then the folders left
        empty (``base`` too, unless it is the store's root), deepest first; a file gone
        meanwhile is skipped, a folder a writer filled again kept. Returns how many
        files; ``stop`` set ends the walk early."""
        removed = 0
        for folder, _dirs, files in os.walk(base, topdown=False):
            if stop is not None and stop.is_set():
                break
            for name in files:
                file = Path(folder, name)
                try:
                    if remove(file):
                        file.unlink()
                        removed += 1
                except FileNotFoundError:
                    continue
            if Path(folder) != self.root:
                try:
                    os.rmdir(folder)
                except OSError:
                    pass
        return removed
