"""Fixtures for the CLI tests: the real ``mcam`` console script in a subprocess (and, for
``mcam device`` and ``mcam simulate-device``, a camera and its daemon wired by a pty path)."""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import pytest
import redis

from models.hdr_io import write_exr
from service.cli.main import main
from tests.device.conftest import health, wait_for

MCAM = Path(sys.executable).parent / "mcam"
#: The issue's example flags: mantissa, alpha 2, 8 bits, 20 % of pixels over x = 1.
SIMULATE_FLAGS = ("--encoding", "mantissa", "--alpha", "2", "--bits", "8", "--overexposed", "0.2")


def run_mcam(*args: str | Path, cwd: Path) -> subprocess.CompletedProcess[str]:
    """Run ``mcam ARGS`` in ``cwd``; stdout and stderr captured as text."""
    return subprocess.run(
        [str(MCAM), *(str(arg) for arg in args)],
        cwd=cwd,
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )


def run_mcams(
    commands: list[tuple[str | Path, ...]], cwd: Path, env: dict[str, str] | None = None
) -> list[subprocess.CompletedProcess[str]]:
    """``mcam ARGS`` for each ARGS in ``commands``, as :func:`run_mcam` runs it, but all
    at once (each spends nearly all its time importing); results in the same order. Any
    still running after 120 s is killed (a command that refused nothing may run on)."""
    processes = [
        subprocess.Popen(
            [str(MCAM), *(str(arg) for arg in args)],
            cwd=cwd, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
        )  # fmt: skip
        for args in commands
    ]
    try:
        return [
            subprocess.CompletedProcess(process.args, process.returncode, out, err)
            for process in processes
            for out, err in [process.communicate(timeout=120)]
        ]
    finally:
        for process in processes:
            if process.poll() is None:
                process.kill()
                process.communicate()


def mcam_in_process(
    capsys: pytest.CaptureFixture[str], *args: str | Path
) -> subprocess.CompletedProcess[str]:
    """``mcam ARGS`` through the console script's own entry point (:func:`main`) in this
    process: its exit code (argparse's ``SystemExit`` included) and what it printed. Only
    for arguments refused before anything runs, which then cost no fresh interpreter (a
    second or two of imports each); keep one :func:`run_mcam` check of such a refusal per
    command, for what only the real console script shows."""
    argv = [str(arg) for arg in args]
    capsys.readouterr()
    try:
        code = main(argv)
    except SystemExit as stopped:
        code = stopped.code
    out, err = capsys.readouterr()
    return subprocess.CompletedProcess(["mcam", *argv], code, out, err)


def assert_one_line_error(result: subprocess.CompletedProcess[str], *fragments: str) -> None:
    """Exit code 2, one line on stderr holding every fragment, and no traceback."""
    assert result.returncode == 2, result.stderr
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1, result.stderr
    assert lines[0].startswith("mcam "), lines[0]
    for fragment in fragments:
        assert fragment in lines[0]


def blob_scene(
    size: int = 64, peak: float = 1000.0, halving: float = 3.0, rgb: bool = False
) -> np.ndarray:
    """A smooth blob ``peak * 2^(-r / halving)`` on a dim floor (r: pixels from the centre).

    Its log falls by ``1 / halving`` octaves per pixel, so with the issue's exposure a
    mantissa frame (alpha 2) wraps up to 6 times while neighbours differ by < 1/2 wrap.
    """
    yy, xx = np.mgrid[0:size, 0:size] - (size - 1) / 2.0
    luma = 1e-3 + peak * 2.0 ** (-np.hypot(xx, yy) / halving)
    return np.stack([luma, luma * 0.7, luma * 0.4], axis=2) if rgb else luma


def mantissa_tolerance(reference: np.ndarray, gain: float, bits: int, alpha: float) -> np.ndarray:
    """Largest error of a mantissa reconstruction with the right W, in scene units.

    Half a code bin: ``2^-(bits+1)`` in x below saturation, a factor
    ``alpha^(2^-(bits+1))`` above; plus float32 rounding of both stored images.
    """
    x = reference * gain
    half_bin = 2.0 ** -(bits + 1)
    bound = np.where(x < 1.0, half_bin, x * (alpha**half_bin - 1.0)) / gain
    return bound + 2.0**-22 * reference


@pytest.fixture(scope="session")
def pipeline(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A folder after ``mcam simulate`` and ``mcam reconstruct --decoder itoh`` on a blob.

    Holds scene.exr, wrapped.png, W_true.png, reference.exr, hdr.exr, W.png and
    the commands' stdout in simulate.out / reconstruct.out.
    """
    folder = tmp_path_factory.mktemp("pipeline")
    write_exr(folder / "scene.exr", blob_scene())
    simulate = run_mcam(
        "simulate", "scene.exr", "-o", "wrapped.png", *SIMULATE_FLAGS,
        "--ground-truth", "W_true.png", "--reference-out", "reference.exr",
        cwd=folder,
    )  # fmt: skip
    assert simulate.returncode == 0, simulate.stderr
    reconstruct = run_mcam(
        "reconstruct", "wrapped.png", "-o", "hdr.exr", "--decoder", "itoh",
        "--winding-out", "W.png",
        cwd=folder,
    )  # fmt: skip
    assert reconstruct.returncode == 0, reconstruct.stderr
    (folder / "simulate.out").write_text(simulate.stdout)
    (folder / "reconstruct.out").write_text(reconstruct.stdout)
    return folder


def env_for(redis_url: str, data_dir: Path) -> dict[str, str]:
    """This environment with ``MCAM_REDIS_URL`` and ``MCAM_DATA_DIR`` set: an ``mcam``
    process's settings."""
    return {**os.environ, "MCAM_REDIS_URL": redis_url, "MCAM_DATA_DIR": str(data_dir)}


@contextmanager
def camera_and_daemon(env: dict[str, str], client: redis.Redis, tmp_path: Path,
                      *camera_flags: str) -> Iterator[None]:
    """``mcam simulate-device`` on a pty and ``mcam device`` (device ``rig-1``) reading
    it, both run with ``env``; once the daemon has a frame (``client``: its Redis),
    yields; both must then stop cleanly on SIGTERM."""
    camera = subprocess.Popen(
        [MCAM, "simulate-device", "--port", f"pty:{tmp_path / 'cam'}", "--fps", "30",
         *camera_flags],
        stdout=subprocess.PIPE, stderr=(tmp_path / "camera.log").open("w"), text=True, env=env,
        cwd=tmp_path)
    daemon = None
    try:
        assert camera.stdout is not None
        url = camera.stdout.readline().strip()
        assert url == str(tmp_path / "cam") and Path(url).exists()
        daemon = subprocess.Popen([MCAM, "device", "--port", url, "--device-id", "rig-1"],
                                  stdout=subprocess.DEVNULL,
                                  stderr=(tmp_path / "daemon.log").open("w"), text=True,
                                  env=env, cwd=tmp_path)
        assert wait_for(lambda: health(client, "rig-1").get("frames_ok", "0") != "0", 60)
        yield
    finally:
        for process in (daemon, camera):
            if process is not None:
                process.send_signal(signal.SIGTERM)
    assert daemon is not None and daemon.wait(20) == 0
    assert camera.wait(20) == 0


#: Sends SIGINT and SIGTERM in turn to process argv[1], as fast as it can, until killed.
SIGNAL_FLOOD = """
import os, signal, sys
pid = int(sys.argv[1])
while True:
    os.kill(pid, signal.SIGINT)
    os.kill(pid, signal.SIGTERM)
"""


@contextmanager
def stopped_by_signal_flood(process: subprocess.Popen[str]) -> Iterator[list[str]]:
    """Once the body has seen ``process`` (stderr piped, as text) running, flood it with
    SIGINT and SIGTERM from another process until it exits (30 s at most: then it is
    killed and the test fails). Yields a list that then holds the process's stderr."""
    output: list[str] = []
    flood = None
    try:
        yield output
        flood = subprocess.Popen([sys.executable, "-c", SIGNAL_FLOOD, str(process.pid)],
                                 stderr=subprocess.DEVNULL)
        with contextlib.suppress(subprocess.TimeoutExpired):
            process.wait(30)
    finally:
        if flood is not None:
            flood.kill()
            flood.wait(30)
        hung = process.poll() is None
        if hung:
            process.kill()
        output.append(process.communicate(timeout=60)[1])
    assert not hung, f"still running under the signals: {output[0]}"
