"""Whether the installed model files are the ones their cards describe, for the API's
readiness check. A file whose sha256 is not its card's (cut short, corrupt, replaced, a
Git LFS pointer), or that is gone since the service started, makes every job that needs
it fail as ``model_unavailable``, while the decoder is still listed and the service would
otherwise say it is ready. Each file is hashed once per size, modification and change
times, mode and owner (:func:`stat_key`), so a poll costs a ``stat`` per card."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

from models.decoders import learned
from models.decoders.learned import RESTORE_ADVICE, load_cards, read_cards, sha256_of

#: Per ONNX file: (its :func:`stat_key`, the card's sha256) -> whether it matched.
_CHECKED: dict[Path, tuple[tuple[tuple[int, ...], str], bool]] = {}


def stat_key(stat: os.stat_result) -> tuple[int, ...]:
    """What of a file's ``stat`` a cached hash check of it holds for: its size (bytes),
    modification and change times (ns), mode and owner. A ``chmod 000`` keeps the size
    and the mtime: keyed on those alone, a file made unreadable stayed its card's while
    loading it failed. A chmod, chown or ACL change moves the change time; the mode and
    owner are kept too for file systems that do not keep it."""
    return (
        stat.st_size,
        stat.st_mtime_ns,
        stat.st_ctime_ns,
        stat.st_mode,
        stat.st_uid,
        stat.st_gid,
    )


def file_matches(path: Path, sha256: str) -> bool:
    """Whether the file at ``path`` exists, can be read and its sha256 is ``sha256``
    (cached by its :func:`stat_key`, so a file whose permissions or owner change is read
    again; a file removed since, or one that cannot be read, such as a directory in its
    place or a file without read permission, is not its card's and is not cached)."""
    try:
        stat = path.stat()
    except OSError:
        return False
    key = (stat_key(stat), sha256)
    cached = _CHECKED.get(path)
    if cached is not None and cached[0] == key:
        return cached[1]
    try:
        matches = sha256_of(path) == sha256
    except OSError:
        return False
    _CHECKED[path] = (key, matches)
    return matches


def broken_models(onnx_dir: Path | None = None) -> list[str]:
    """One line per model installed in ``onnx_dir`` (None: the served one,
    :data:`models.decoders.learned.ONNX_DIR`) whose ONNX file is missing, cannot be read
    or is not the one its card describes: the file's name (no server path), its decoder
    and encoding, what follows and what to do. Empty when every installed file is its
    card's."""
    folder = onnx_dir or learned.ONNX_DIR
    missing = [broken(card, "is missing") for _, card in read_cards(folder, with_file=False)]
    return missing + [
        broken(card, "cannot be read or is not the one its card describes")
        for card in load_cards(folder)
        if not file_matches(Path(card["path"]), str(card["sha256"]))
    ]


def broken(card: dict[str, Any], problem: str) -> str:
    """The readiness line of ``card``'s model file with ``problem`` (what is wrong with
    it): its name without a folder, its decoder and encoding, what follows and what to do."""
    return (
        f"model file {Path(card['file']).name} (decoder {card['decoder']!r}, "
        f"{card['encoding']} frames) {problem}, so jobs that need it fail as "
        f"model_unavailable; {RESTORE_ADVICE}"
    )
