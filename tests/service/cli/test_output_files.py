"""Tests of service/cli/output_files.py: outputs checked up front, written whole or not at all."""

from __future__ import annotations

import os
import signal
from pathlib import Path

import pytest

from models.errors import InvalidInputError, UnsupportedFormatError
from service.cli.output_files import OutputFile, check_inputs, check_outputs, staged_outputs
from tests.service.cli.conftest import assert_one_line_error, run_mcam

EXR = (".exr",)


def exr(flag: str, path: Path | str) -> OutputFile:
    return OutputFile(flag, str(path), "a reconstruction is written as OpenEXR", EXR)


@pytest.mark.parametrize(
    ("outputs", "inputs", "error", "message"),
    [
        ([exr("-o", "x.png")], [], UnsupportedFormatError, "-o x.png: .* name the file .exr"),
        ([exr("-o", "d.exr/")], [], InvalidInputError, "names a folder"),
        ([exr("-o", "a.exr"), exr("--w", "./a.exr")], [], InvalidInputError, "both name"),
        ([exr("-o", "in.exr")], ["in.exr"], InvalidInputError, "is the input file"),
        ([exr("-o", "nofolder/a.exr")], [], InvalidInputError, "no such folder: nofolder"),
        # It was told "-o .exr: ...; name the file .exr", which it is (Path's suffix "").
        ([exr("-o", ".exr")], [], InvalidInputError, r"-o \.exr has no name before its suffix"),
        ([exr("-o", "d/.EXR")], [], InvalidInputError, r"\.EXR; give the file a name, e.g. d/out"),
    ],
)
def test_bad_outputs_are_refused_before_any_work(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, outputs: list[OutputFile],
    inputs: list[str], error: type[Exception], message: str,
) -> None:  # fmt: skip
    monkeypatch.chdir(tmp_path)
    (tmp_path / "in.exr").write_bytes(b"scene")
    with pytest.raises(error, match=message):
        check_outputs(outputs, inputs)


def test_outputs_move_into_place_only_when_all_succeeded(tmp_path: Path) -> None:
    outputs = [exr("-o", tmp_path / "a.exr"), exr("--w", tmp_path / "b.exr")]
    with pytest.raises(RuntimeError):
        with staged_outputs(outputs) as paths:
            paths["-o"].write_bytes(b"done")
            raise RuntimeError("the second output failed")
    assert os.listdir(tmp_path) == []
    with staged_outputs(outputs) as paths:
        assert paths["-o"].parent == tmp_path and paths["-o"].suffix == ".exr"
        for path in paths.values():
            path.write_bytes(b"done")
    assert sorted(os.listdir(tmp_path)) == ["a.exr", "b.exr"]
    umask = os.umask(0)
    os.umask(umask)
    assert (tmp_path / "a.exr").stat().st_mode & 0o777 == 0o666 & ~umask


def test_an_output_that_is_a_symbolic_link_writes_the_file_it_leads_to(tmp_path: Path) -> None:
    """``-o latest.exr`` (a link to ``runs/hdr.exr``) replaced the link with a file and
    left ``runs/hdr.exr`` as it was; a shell's ``>`` writes through the link. A link
    into a folder that does not exist is refused naming that folder."""
    (tmp_path / "runs").mkdir()
    (tmp_path / "latest.exr").symlink_to(tmp_path / "runs" / "hdr.exr")
    with staged_outputs([exr("-o", tmp_path / "latest.exr")]) as paths:
        assert paths["-o"].parent == tmp_path / "runs" and paths["-o"].suffix == ".exr"
        paths["-o"].write_bytes(b"done")
    assert (tmp_path / "latest.exr").is_symlink()
    assert (tmp_path / "runs" / "hdr.exr").read_bytes() == b"done"
    assert sorted(os.listdir(tmp_path / "runs")) == ["hdr.exr"]
    (tmp_path / "gone.exr").symlink_to(tmp_path / "nowhere" / "hdr.exr")
    with pytest.raises(InvalidInputError, match=f"no such folder: {tmp_path / 'nowhere'} "):
        check_outputs([exr("-o", tmp_path / "gone.exr")])


@pytest.mark.parametrize("stem", ["a" * 251, "é" * 125 + "a"])
def test_an_output_whose_name_is_near_the_longest_allowed_is_written(
    tmp_path: Path, stem: str
) -> None:
    """A name of 241 to 255 bytes is a valid file name, but its temporary file's, 15 bytes
    longer, was not: 'cannot create ... (File name too long) for -o; choose a folder you
    may write to'."""
    name = stem + ".exr"
    assert len(name.encode()) == 255  # the longest a file name may be (NAME_MAX)
    with staged_outputs([exr("-o", tmp_path / name)]) as paths:
        assert paths["-o"].suffix == ".exr" and paths["-o"].name.startswith(".")
        paths["-o"].write_bytes(b"done")
    assert os.listdir(tmp_path) == [name]


def test_an_uncreatable_output_names_its_path() -> None:
    with pytest.raises(InvalidInputError, match="cannot create /proc/x.exr .* for -o"):
        with staged_outputs([exr("-o", "/proc/x.exr")]):
            pass


def test_a_writer_failing_on_its_temporary_file_names_the_output(tmp_path: Path) -> None:
    target = tmp_path / "clip.mp4"
    with pytest.raises(OSError) as failure:
        with staged_outputs([OutputFile("-o", str(target), "a video", (".mp4",))]) as paths:
            raise OSError(28, "No space left on device", str(paths["-o"]))
    assert failure.value.filename == str(target) and failure.value.strerror.startswith("No space")
    assert list(tmp_path.iterdir()) == []


def test_sigterm_removes_the_temporary_files_and_exits_143(tmp_path: Path) -> None:
    """SIGTERM (``timeout``, ``kill``) during a long decode ended the process at once and
    left the hidden temporary output behind; now it unwinds like Ctrl-C, exiting 143.
    The caller's handler (here the test's, standing in for the default) comes back."""
    received: list[int] = []
    previous = signal.signal(signal.SIGTERM, lambda signum, _frame: received.append(signum))
    try:
        with pytest.raises(SystemExit) as stopped:
            with staged_outputs([exr("-o", tmp_path / "a.exr")]) as paths:
                assert paths["-o"].exists()
                os.kill(os.getpid(), signal.SIGTERM)
        assert stopped.value.code == 143 and received == []
        assert list(tmp_path.iterdir()) == []
        os.kill(os.getpid(), signal.SIGTERM)
        assert received == [signal.SIGTERM]
    finally:
        signal.signal(signal.SIGTERM, previous)


@pytest.mark.parametrize(
    "command",
    [
        ("video", "e.npy", "-o", "x.mp4", "--encoding", "mantissa", "--alpha", "2", "--bits", "8"),
        ("reconstruct", "e.npy", "-o", "x.exr", "--encoding", "mantissa", "--alpha", "2"),
        ("simulate", "e.exr", "-o", "x.png", "--gain", "1"),
    ],
)
def test_an_empty_input_file_is_called_empty(tmp_path: Path, command: tuple[str, ...]) -> None:
    """An empty input was called "not an npy file (bad or missing signature)" (or not an
    OpenEXR image) where the API says the uploaded file is empty."""
    (tmp_path / command[1]).write_bytes(b"")
    done = run_mcam(*command, cwd=tmp_path)
    assert done.returncode == 2
    assert f"the file {command[1]} is empty; send the whole file" in done.stderr
    assert not (tmp_path / command[3]).exists()


def test_an_input_folder_is_called_a_folder(tmp_path: Path) -> None:
    """A folder given as the frame (or a W map) was "unsupported wrapped-frame format
    'frames'; use one of: .png ...", as if the file were of another format."""
    (tmp_path / "frames").mkdir()
    with pytest.raises(IsADirectoryError):
        check_inputs([str(tmp_path / "frames")])
    result = run_mcam("reconstruct", "frames", "-o", "x.exr", cwd=tmp_path)
    assert_one_line_error(result, "frames is a folder; give the path of a file")
    assert not (tmp_path / "x.exr").exists()
