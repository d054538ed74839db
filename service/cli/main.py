"""Entry point of the ``mcam`` console script.

Each command lives in its own module exposing ``register(subparsers)``, which
adds a sub-parser whose ``func`` default runs the command and returns an exit
code. Errors that are the caller's (:class:`McamError`, a missing file, an
``MCAM_*`` setting that does not parse) print one clear line and exit 2; they never
show a traceback.
"""

from __future__ import annotations

import argparse
import errno
import importlib
import os
import signal
import sys
from pathlib import Path

from pydantic import ValidationError
from pydantic_core import ErrorDetails

from models.allocator import keep_freed_memory
from models.errors import McamError

#: Command modules, in the order ``mcam --help`` lists them.
COMMANDS: tuple[str, ...] = (
    "service.cli.simulate",
    "service.cli.reconstruct",
    "service.cli.evaluate",
    "service.cli.api",
    "service.cli.worker",
    "service.cli.serve",
    "service.cli.device",
    "service.cli.simulate_device",
    "service.cli.train",
    "service.cli.video",
)
#: Each command's name (as ``mcam`` is given it) and its module.
COMMAND_MODULES: dict[str, str] = {
    name.rsplit(".", 1)[1].replace("_", "-"): name for name in COMMANDS
}


def build_parser(command: str | None = None) -> argparse.ArgumentParser:
    """The root parser with every registered command, or with ``command`` alone when
    it is one of them (only its module is imported: ``mcam simulate`` starts in a
    quarter of a second instead of importing the service, about 1.3 s)."""
    parser = argparse.ArgumentParser(
        prog="mcam", description="MantissaCam: snapshot HDR from wrapping sensors"
    )
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    named = COMMAND_MODULES.get(command or "")
    for name in (named,) if named else COMMANDS:
        importlib.import_module(name).register(sub)
    return parser


#: Settings whose value may hold a password: an error names them without the value
#: (the message shows it masked).
SECRET_SETTINGS = ("redis_url",)


def settings_problems(exc: ValidationError) -> str:
    """One line naming each ``MCAM_*`` setting that could not be read, and why; a
    problem of several settings together names them itself."""
    problems = [setting_problem(error) for error in exc.errors()]
    return "invalid settings (environment or .env): " + "; ".join(problems)


def setting_problem(error: ErrorDetails) -> str:
    """One of :func:`settings_problems`: the variable, its value (unless secret), why."""
    if not error["loc"]:
        return error["msg"]
    name = ".".join(str(part) for part in error["loc"])
    if name in SECRET_SETTINGS:
        return f"MCAM_{name.upper()}: {error['msg']}"
    return f"MCAM_{name.upper()}={error.get('input')!r}: {error['msg']}"


#: What to do, by ``errno``, about a path on a filesystem that takes no more writes
#: (the data dir of ``mcam serve`` on a read-only mount or a full disk, an output file),
#: or one that passes through a file (``MCAM_DATA_DIR`` naming a file).
FILESYSTEM_REMEDIES: dict[int | None, str] = {
    errno.EROFS: "; choose a path on a writable filesystem (or remount it read-write)",
    errno.ENOSPC: "; free space on its disk or choose a path on another disk",
    errno.EDQUOT: "; free space within your disk quota or choose a path on another disk",
    errno.ENOTDIR: "; a part of that path is a file, not a folder: choose another path",
}


def file_problem(exc: OSError) -> str:
    """One line for a file the command could not read or write, saying what to change."""
    if exc.filename is None:
        return exc.strerror or str(exc)
    # Of a link or rename, the path being created (the second) is the one to fix.
    path = Path(exc.filename2 if exc.filename2 is not None else exc.filename)
    if isinstance(exc, FileNotFoundError):
        if not path.parent.exists():
            return f"no such folder: {path.parent} (for {path}); create it or choose another path"
        return f"no such file: {path}"
    if isinstance(exc, IsADirectoryError):
        return f"{path} is a folder; give the path of a file (in it or elsewhere)"
    if isinstance(exc, PermissionError):
        return f"permission denied: {path}; choose a path you may read or write"
    return f"cannot use {path}: {exc.strerror or exc}{FILESYSTEM_REMEDIES.get(exc.errno, '')}"


#: Exit status of a command whose output's reader went away (128 + SIGPIPE, as a shell
#: reports a process that SIGPIPE ended).
READER_GONE = 141


def reader_gone() -> int:
    """The reader of our standard output went away (``mcam ... | head``): stop quietly,
    as other command-line tools do, and point standard output at the null device so
    that Python's final flush does not fail again."""
    try:
        null = os.open(os.devnull, os.O_WRONLY)
        os.dup2(null, sys.stdout.fileno())
    except (OSError, ValueError):
        pass
    return READER_GONE


def main(argv: list[str] | None = None) -> int:
    """Parse arguments, run the command, map caller errors to exit code 2 (a reader that
    went away to :data:`READER_GONE` and Ctrl-C to 130, silently). Freed memory
    stays in the process for reuse (:func:`models.allocator.keep_freed_memory`)."""
    keep_freed_memory()
    argv = sys.argv[1:] if argv is None else argv
    try:
        return run_command(argv)
    except KeyboardInterrupt:
        return interrupted()


def interrupted() -> int:
    """Exit status 130 for a Ctrl-C, further ones ignored: only the interpreter's exit is
    left, and it gives SIGINT its default action back, so a second Ctrl-C ended the
    process by SIGINT (exit -2, no message)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    return 130


def run_command(argv: list[str]) -> int:
    """Import the command, parse ``argv`` and run it; :func:`main` without Ctrl-C's
    handling. Importing a command takes a second or more (``mcam serve``: the service),
    and Ctrl-C meanwhile printed a traceback of the import."""
    args = build_parser(argv[0] if argv else None).parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except BrokenPipeError:
        return reader_gone()
    except McamError as exc:
        print(f"mcam {args.command}: error: {exc.message}", file=sys.stderr)
        return 2
    except OSError as exc:
        print(f"mcam {args.command}: error: {file_problem(exc)}", file=sys.stderr)
        return 2
    except ValidationError as exc:
        print(f"mcam {args.command}: error: {settings_problems(exc)}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
