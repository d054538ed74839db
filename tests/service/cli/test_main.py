"""service/cli/main.py: a file the command cannot read or write is one clear line, exit 2;
a command imports only its own module."""

from __future__ import annotations

import argparse
import errno
import os
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from pydantic import ValidationError

import service.cli.main as cli_main
from service.cli.main import (
    COMMAND_MODULES,
    READER_GONE,
    build_parser,
    file_problem,
    main,
    settings_problems,
)
from service.core.config import Settings

FLAGS = ("--encoding", "mantissa", "--alpha", "2", "--bits", "8")


@pytest.mark.parametrize(
    ("error", "expected"),
    [
        (FileNotFoundError(errno.ENOENT, "No such file", "/no/such/dir/x.exr"), "no such folder"),
        (IsADirectoryError(errno.EISDIR, "Is a directory", "/tmp"), "is a folder"),
        (PermissionError(errno.EACCES, "Permission denied", "/root/x"), "permission denied"),
        (OSError(errno.EIO, "Input/output error", "/proc/version"), "cannot use /proc/version"),
        (OSError(errno.EADDRINUSE, "Address already in use"), "Address already in use"),
    ],
    ids=["missing-folder", "folder", "permission", "io", "no-file-name"],
)
def test_file_problem_says_what_to_change(error: OSError, expected: str) -> None:
    line = file_problem(error)
    assert expected in line and "\n" not in line


@pytest.mark.parametrize(
    ("error", "remedy"),
    [
        (OSError(errno.EROFS, "Read-only file system", "/mnt/ro/data"), "writable filesystem"),
        (OSError(errno.ENOSPC, "No space left on device", "/mnt/full/data"), "free space"),
        (OSError(errno.EDQUOT, "Disk quota exceeded", "/home/u/data"), "disk quota"),
    ],
    ids=["read-only", "full", "quota"],
)
def test_a_filesystem_taking_no_writes_is_told_what_to_do(error: OSError, remedy: str) -> None:
    """A data dir on a read-only mount stopped `mcam serve` with "cannot use /mnt/ro/data:
    Read-only file system", which said nothing of what to do."""
    line = file_problem(error)
    assert line.startswith(f"cannot use {error.filename}: {error.strerror}; ")
    assert remedy in line


def test_a_path_through_a_file_is_told_what_to_do(tmp_path: Path) -> None:
    """MCAM_DATA_DIR naming a file stopped `mcam serve` with "cannot use FILE/redis: Not
    a directory", and nothing of what to do."""
    (tmp_path / "data").write_text("")
    with pytest.raises(NotADirectoryError) as caught:
        (tmp_path / "data" / "redis").mkdir()
    assert file_problem(caught.value) == (
        f"cannot use {tmp_path / 'data' / 'redis'}: Not a directory; a part of that path "
        "is a file, not a folder: choose another path"
    )


def test_a_link_names_the_path_it_creates(tmp_path: Path) -> None:
    link = tmp_path / "missing" / "cam"
    with pytest.raises(FileNotFoundError) as caught:
        link.symlink_to("/dev/null")
    assert file_problem(caught.value).startswith(f"no such folder: {link.parent}")


def test_missing_input_file_is_named(tmp_path: Path) -> None:
    error = FileNotFoundError(errno.ENOENT, "No such file", str(tmp_path / "nope.png"))
    assert file_problem(error) == f"no such file: {tmp_path / 'nope.png'}"


def test_a_problem_of_several_settings_is_its_own_words() -> None:
    """A check of settings together (no one setting to blame) was printed as
    "MCAM_={...every setting...}: Value error, ..."."""
    with pytest.raises(ValidationError) as caught:
        Settings(_env_file=None, jobs_max_bytes=200_000_000, redis_maxmemory=250_000_000)
    line = settings_problems(caught.value)
    assert line.startswith("invalid settings (environment or .env): Value error, "
                           "MCAM_REDIS_MAXMEMORY (250000000) is below")
    assert "MCAM_=" not in line and "\n" not in line


def test_a_redis_url_refused_is_not_shown_with_its_password() -> None:
    """MCAM_REDIS_URL holds the Redis password: the line names it, and the message shows
    the URL masked."""
    with pytest.raises(ValidationError) as caught:
        Settings(_env_file=None, redis_url="redis://:s3cret@localhost:notaport")
    line = settings_problems(caught.value)
    assert "MCAM_REDIS_URL: " in line and "redis://:***@localhost:notaport" in line
    assert "s3cret" not in line


@pytest.mark.parametrize("output", [".", "missing/x.exr"], ids=["a-folder", "no-folder"])
def test_unwritable_output_exits_2_without_a_traceback(
    tmp_path: Path, output: str, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.chdir(tmp_path)
    np.save(tmp_path / "frame.npy", np.zeros((8, 8), np.uint8))
    assert main(["reconstruct", "frame.npy", "-o", output, "--decoder", "itoh", *FLAGS]) == 2
    err = capsys.readouterr().err
    assert err.startswith("mcam reconstruct: error: ") and "Traceback" not in err
    assert len(err.strip().splitlines()) == 1


def test_a_reader_that_goes_away_ends_the_command_quietly(tmp_path: Path) -> None:
    """``mcam ... | head``: the pipe's reader is gone before the command writes."""
    read_end, write_end = os.pipe()
    os.close(read_end)
    try:
        done = subprocess.run(
            [sys.executable, "-m", "service.cli.main", "reconstruct", "--list-decoders"],
            stdout=write_end, stderr=subprocess.PIPE, text=True, timeout=120, check=False,
        )
    finally:
        os.close(write_end)
    assert done.returncode == READER_GONE
    assert done.stderr == ""


def commands(parser: argparse.ArgumentParser) -> set[str]:
    """The command names ``parser`` accepts."""
    [sub] = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
    return set(sub.choices)


def test_a_named_command_builds_its_own_parser_alone() -> None:
    assert commands(build_parser()) == set(COMMAND_MODULES)
    for name in COMMAND_MODULES:
        assert commands(build_parser(name)) == {name}
    for other in (None, "", "simulat", "simulate_device", "--help"):
        assert commands(build_parser(other)) == set(COMMAND_MODULES)


def test_a_command_does_not_import_the_others() -> None:
    """Every command imported every command's module (the service, the worker): 1.3 s
    before mcam simulate-device could refuse a flag."""
    probe = (
        "import sys; from service.cli.main import main; "
        "status = main(['simulate-device', '--fps', '1e-300']); "
        "print(status, sorted(m for m in ('fastapi', 'service.api.state', 'worker.runner') "
        "if m in sys.modules))"
    )
    done = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True,
                          timeout=60, check=False)  # fmt: skip
    assert done.stdout.strip() == "2 []", done.stdout + done.stderr
    assert "--fps must be from 0.1 to 10000" in done.stderr


def test_ctrl_c_while_a_command_imports_exits_130_without_a_traceback(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Importing ``mcam serve``'s modules takes over a second; Ctrl-C meanwhile (a
    KeyboardInterrupt in build_parser) printed the import's traceback, exit -2."""

    def interrupted(command: str | None = None) -> argparse.ArgumentParser:
        raise KeyboardInterrupt

    monkeypatch.setattr(cli_main, "build_parser", interrupted)
    previous = signal.getsignal(signal.SIGINT)
    try:
        code = main(["serve"])
        ignored = signal.getsignal(signal.SIGINT)
    except KeyboardInterrupt:
        pytest.fail("Ctrl-C during the import escaped main (a traceback)")
    finally:
        signal.signal(signal.SIGINT, previous)
    assert code == 130
    # The exit is left alone: the interpreter's exit gave SIGINT its default action back,
    # and a second Ctrl-C then ended the process by SIGINT (exit -2, no message).
    assert ignored == signal.SIG_IGN
