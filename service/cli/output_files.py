"""The files a command writes: checked before any work, written whole or not at all.

A command lists its outputs (:class:`OutputFile`: the flag naming it, the path, the
suffixes its format allows) and runs inside :func:`staged_outputs`, which

- refuses, before any input is read, a wrong suffix, a path naming a folder, a
  missing folder, two outputs naming one file, an output naming an input, and an
  input that is a folder or an empty file (:func:`check_inputs`);
- creates each output as a hidden temporary file in its own folder (so an unwritable
  folder is found at once, and a rename puts it in place atomically) with the final
  suffix (writers pick the format from it);
- moves every temporary file into place only when the whole command succeeded, and
  removes them all otherwise: a failed command leaves no partial or stale-looking output;
- meanwhile ends the command on SIGTERM (``timeout``, ``kill``) as on Ctrl-C, through
  that cleanup, with exit status 143 (128 + SIGTERM).
"""

from __future__ import annotations

import errno
import os
import secrets
import signal
import sys
import threading
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from types import FrameType

from models.errors import InvalidInputError, UnsupportedFormatError
from models.file_magic import refuse_empty

#: The most bytes a file name may hold (NAME_MAX of Linux, macOS and Windows file systems).
NAME_MAX = 255


@dataclass(frozen=True)
class OutputFile:
    """One file to write: ``flag`` names it (``-o``), ``path`` as given, ``what`` says how
    it is written (``"a reconstruction is written as OpenEXR"``) and the ``suffixes`` its
    format may have (lower case, first preferred)."""

    flag: str
    path: str
    what: str
    suffixes: tuple[str, ...]

    @property
    def target(self) -> Path:
        """The file written: ``path``, or the file it leads to through symbolic links
        (``-o latest.exr``, a link to ``runs/7/hdr.exr``, writes ``runs/7/hdr.exr`` and
        keeps the link, as a shell's ``>`` does; the link was replaced by a file)."""
        return Path(os.path.realpath(self.path))

    def check_name(self) -> None:
        """Refuse a path that names a folder, is a suffix alone (``.exr``) or has a suffix
        of another format."""
        if self.path.endswith(("/", os.sep)) or Path(self.path).is_dir():
            raise InvalidInputError(
                f"{self.flag} {self.path} names a folder; give the path of a file, e.g. "
                f"{Path(self.path.rstrip('/' + os.sep)) / ('out' + self.suffixes[0])}"
            )
        name = Path(self.path).name
        if name.lower() in self.suffixes:  # ".exr": a hidden file, its suffix ""
            raise InvalidInputError(
                f"{self.flag} {self.path} has no name before its suffix {name}; give the "
                f"file a name, e.g. {Path(self.path).with_name('out' + name)}"
            )
        if Path(self.path).suffix.lower() not in self.suffixes:
            *others, last = self.suffixes
            choices = f"{', '.join(others)} or {last}" if others else last
            raise UnsupportedFormatError(
                f"{self.flag} {self.path}: {self.what}; name the file {choices}"
            )


def _same_file(a: str, b: str) -> bool:
    if os.path.exists(a) and os.path.exists(b):
        return os.path.samefile(a, b)
    return os.path.realpath(a) == os.path.realpath(b)


def check_outputs(outputs: Sequence[OutputFile], inputs: Sequence[str] = ()) -> None:
    """Refuse bad names (:meth:`OutputFile.check_name`), two outputs on one file, an
    output on an input, and a folder that does not exist."""
    for index, output in enumerate(outputs):
        output.check_name()
        for other in outputs[:index]:
            if _same_file(output.path, other.path):
                raise InvalidInputError(
                    f"{other.flag} and {output.flag} both name {output.path}; give each "
                    "output its own file"
                )
        for source in inputs:
            if _same_file(output.path, source):
                raise InvalidInputError(
                    f"{output.flag} {output.path} is the input file; write the output to "
                    "another file"
                )
        folder = Path(output.path).parent
        if folder.is_dir() and not output.target.parent.is_dir():  # a link into no folder
            folder = output.target.parent
        if not folder.is_dir():
            raise InvalidInputError(
                f"no such folder: {folder} (for {output.flag} {output.path}); create it or "
                "choose another path"
            )


def _temporary_name(final: Path) -> str:
    """The hidden name of ``final``'s temporary file: its stem, cut short (at a character)
    where the name would pass :data:`NAME_MAX` bytes, a random tag and its suffix. A
    name of 241 to 255 bytes, valid, was refused as too long for its temporary file."""
    tag = f".mcam-{secrets.token_hex(4)}{final.suffix}"
    room = NAME_MAX - 1 - len(os.fsencode(tag))
    stem = os.fsencode(final.stem)[: max(room, 0)].decode(sys.getfilesystemencoding(), "ignore")
    return f".{stem}{tag}"


def _create_temporary(output: OutputFile) -> Path:
    """An empty hidden file beside ``output.target`` with the suffix of ``output.path``
    (the writers' format), its mode as umask allows."""
    temporary = output.target.with_name(_temporary_name(Path(output.path)))
    try:
        os.close(os.open(temporary, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o666))
    except OSError as exc:
        raise InvalidInputError(
            f"cannot create {output.path} ({exc.strerror or exc}) for {output.flag}; choose "
            "a folder you may write to"
        ) from None
    return temporary


def _named_for_its_output(
    exc: OSError, outputs: Sequence[OutputFile], temporaries: dict[str, Path]
) -> OSError:
    """``exc`` naming the output a writer (PyAV, zipfile, numpy) failed on, instead of its
    temporary file, so that :func:`service.cli.main.file_problem` names the path given."""
    for output in outputs:
        if str(temporaries.get(output.flag)) in (str(exc.filename), str(exc.filename2)):
            return OSError(exc.errno, exc.strerror, output.path)
    return exc


def _exit_on_signal(signum: int, _frame: FrameType | None) -> None:
    raise SystemExit(128 + signum)


@contextmanager
def _sigterm_unwinds() -> Iterator[None]:
    """Within the block, SIGTERM raises :class:`SystemExit` (143) so that the cleanup of
    :func:`staged_outputs` runs: by default it ended the process at once, leaving the
    hidden temporary files behind. Signal handlers belong to the main thread; elsewhere
    the block runs as it is."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = signal.signal(signal.SIGTERM, _exit_on_signal)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


def check_inputs(inputs: Sequence[str]) -> None:
    """Refuse an input that is a folder (:class:`IsADirectoryError`, which
    :func:`service.cli.main.file_problem` words) or an empty regular file (the API's check
    of an upload, :func:`models.file_magic.refuse_empty`): a frame's reader called a
    folder an unsupported format, and an empty file a file of no known format. Missing
    files and pipes are left to the reader."""
    for source in inputs:
        if os.path.isdir(source):
            raise IsADirectoryError(errno.EISDIR, os.strerror(errno.EISDIR), source)
        if os.path.isfile(source):
            refuse_empty(os.path.getsize(source), f"the file {source}")


@contextmanager
def staged_outputs(
    outputs: Sequence[OutputFile], inputs: Sequence[str] = ()
) -> Iterator[dict[str, Path]]:
    """Check the outputs (:func:`check_outputs`), then yield the temporary path to write
    for each flag; on success move each into place, on any failure (SIGTERM included:
    :func:`_sigterm_unwinds`) remove them all."""
    check_outputs(outputs, inputs)
    check_inputs(inputs)
    temporaries: dict[str, Path] = {}
    with _sigterm_unwinds():
        try:
            for output in outputs:
                temporaries[output.flag] = _create_temporary(output)
            yield temporaries
            for output in outputs:
                os.replace(temporaries.pop(output.flag), output.target)
        except OSError as exc:
            raise _named_for_its_output(exc, outputs, temporaries) from None
        finally:
            for temporary in temporaries.values():
                temporary.unlink(missing_ok=True)
