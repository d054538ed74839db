"""Where bracketed reference pairs are stored, and the bound on how many are kept.

A pair lives in ``<data dir>/datasets/<device>/<host ns>-<sequence>/``: the host's wall
clock at saving (ns since the epoch, 20 digits) first, so folder names sort oldest
first and a camera whose sequence counter restarted never overwrites an earlier pair.
A pair is written into a hidden sibling (``.<host ns>-<sequence>``, :func:`new_pair_folder`)
that :func:`finish_pair` renames once every file is in it, so a pair folder is never half
written. After each save :func:`prune_pairs` removes the oldest pairs of that device beyond
a count or a size in bytes. The folders are owner-only (0700).
"""

from __future__ import annotations

import logging
import shutil
import time
from dataclasses import dataclass
from pathlib import Path

from worker.private_dirs import PRIVATE_DIR_MODE, private_dir

log = logging.getLogger(__name__)

#: Sub-folder of the data dir that holds every device's pairs.
DATASETS_DIR = "datasets"
#: Name prefix of a pair folder still being written.
UNFINISHED_PREFIX = "."

#: Default bounds per device: about 300 KB a pair for a 256 x 256 frame.
DEFAULT_MAX_PAIRS = 1000
DEFAULT_MAX_BYTES = 1 << 30


@dataclass(frozen=True)
class DatasetLimits:
    """The most pairs, and the most bytes of their files, one device keeps."""

    max_pairs: int = DEFAULT_MAX_PAIRS
    max_bytes: int = DEFAULT_MAX_BYTES


def device_dir(root: Path, device: str) -> Path:
    """The folder holding one device's pairs."""
    return Path(root) / DATASETS_DIR / device


def new_pair_folder(root: Path, device: str, sequence: int) -> Path:
    """Create and return an empty, hidden folder to write a new pair into
    (``FileExistsError`` if taken); :func:`finish_pair` makes it a pair."""
    folder = device_dir(root, device) / f"{UNFINISHED_PREFIX}{time.time_ns():020d}-{sequence:010d}"
    private_dir(Path(root) / DATASETS_DIR)
    private_dir(folder.parent)
    folder.mkdir(mode=PRIVATE_DIR_MODE)
    return folder


def finish_pair(folder: Path) -> Path:
    """Rename a folder of :func:`new_pair_folder` that holds the whole pair to the pair's
    name (without the leading dot); return the pair folder."""
    return folder.rename(folder.with_name(folder.name.removeprefix(UNFINISHED_PREFIX)))


def pair_folders(root: Path, device: str) -> list[Path]:
    """The device's finished pair folders, oldest first."""
    return sorted(
        path for path in device_dir(root, device).iterdir()
        if path.is_dir() and not path.name.startswith(UNFINISHED_PREFIX)
    )


def _size_bytes(folder: Path) -> int:
    return sum(path.stat().st_size for path in folder.rglob("*") if path.is_file())


def prune_pairs(root: Path, device: str, limits: DatasetLimits) -> list[Path]:
    """Remove the device's oldest pairs until at most ``limits`` remain; return them.

    The newest pair is always kept, even when it alone exceeds ``max_bytes``.
    """
    folders = pair_folders(root, device)
    sizes = [_size_bytes(folder) for folder in folders]
    total, removed = sum(sizes), []
    for folder, size in zip(folders[:-1], sizes, strict=False):
        if len(folders) - len(removed) <= limits.max_pairs and total <= limits.max_bytes:
            break
        shutil.rmtree(folder, ignore_errors=True)
        total -= size
        removed.append(folder)
    if removed:
        log.info("removed the %d oldest dataset pairs of %s (limits: %d pairs, %d bytes): %s",
                 len(removed), device, limits.max_pairs, limits.max_bytes,
                 ", ".join(path.name for path in removed))
    return removed
