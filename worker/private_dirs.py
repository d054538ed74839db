"""Owner-only folders for what the service keeps in its data dir.

Results, bracketed datasets and the embedded Redis's files (its append-only file
holds every job's codes) must not be readable by other local users. Rather than
set a umask for a whole process, each store creates its folder with mode 0700, so
whatever files it writes inside are out of other users' reach.
"""

from __future__ import annotations

import os
import stat
from pathlib import Path

#: Mode of a folder only its owner may list, enter or change.
PRIVATE_DIR_MODE = 0o700
#: Mode of a file only its owner may read or write.
PRIVATE_FILE_MODE = 0o600


def make_private_dirs(path: Path) -> Path:
    """Create ``path`` and its missing parents with mode 0700; existing ones are left as
    they are. Returns ``path``."""
    missing = [folder for folder in (path, *path.parents) if not folder.exists()]
    for folder in reversed(missing):
        folder.mkdir(mode=PRIVATE_DIR_MODE, exist_ok=True)
    return path


def private_dir(path: Path) -> Path:
    """:func:`make_private_dirs`, then narrow ``path`` itself to 0700 when this user owns it
    (a folder an older version created 0755). Returns ``path``."""
    make_private_dirs(path)
    info = path.stat()
    if info.st_uid == os.getuid() and stat.S_IMODE(info.st_mode) != PRIVATE_DIR_MODE:
        os.chmod(path, PRIVATE_DIR_MODE)
    return path
