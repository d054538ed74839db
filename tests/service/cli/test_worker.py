"""``mcam worker`` as a real process: clear errors without Redis, runs against a given one."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from tests.service.cli.conftest import stopped_by_signal_flood
from tests.service.cli.test_serve import read_until, wait_gone
from worker.embedded_redis import EmbeddedRedis, connect
from worker.redis_keys import WORKERS_HEARTBEAT

REPO = Path(__file__).resolve().parents[3]


def mcam(*args: str, env: dict[str, str]) -> subprocess.Popen[str]:
    clean = {k: v for k, v in os.environ.items() if not k.startswith("MCAM_")}
    return subprocess.Popen(
        [sys.executable, "-m", "service.cli.main", *args],
        cwd=REPO,
        env={**clean, **env},
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )


def test_worker_without_redis_explains_what_to_do(tmp_path: Path) -> None:
    process = mcam("worker", env={"MCAM_DATA_DIR": str(tmp_path)})
    _out, err = process.communicate(timeout=60)
    assert process.returncode == 2
    assert "no Redis" in err and "MCAM_REDIS_URL" in err and "Traceback" not in err


@pytest.mark.parametrize("flag", ["--concurrency", "--threads", "--stream-processes"])
def test_worker_rejects_zero_concurrency_or_stream_processes(tmp_path: Path, flag: str) -> None:
    """The refusal named all three flags ("--concurrency, --threads and --stream-processes
    must be at least 1"), not the one given, nor its value."""
    process = mcam("worker", flag, "-2", env={"MCAM_DATA_DIR": str(tmp_path)})
    _out, err = process.communicate(timeout=60)
    assert process.returncode == 2 and "Traceback" not in err
    assert f"error: {flag} must be at least 1 (" in err and "got -2" in err
    assert err.count("--") == 1


@pytest.mark.parametrize(
    "command", [["worker"], ["device", "--port", "loop://", "--device-id", "rig1"]]
)
def test_an_unknown_log_level_is_refused_with_one_line(tmp_path: Path, command: list[str]) -> None:
    process = mcam(*command, "--log-level", "bogus", env={"MCAM_DATA_DIR": str(tmp_path)})
    _out, err = process.communicate(timeout=60)
    assert process.returncode == 2 and "invalid choice: 'BOGUS'" in err
    assert "Traceback" not in err


def test_worker_finds_the_embedded_redis_and_stops_on_sigterm(tmp_path: Path) -> None:
    with EmbeddedRedis(tmp_path) as url:
        client = connect(url)
        process = mcam(
            "worker",
            "--concurrency",
            "2",
            env={"MCAM_DATA_DIR": str(tmp_path), "MCAM_HEARTBEAT_S": "0.2"},
        )
        try:
            deadline = time.monotonic() + 60
            while not client.hlen(WORKERS_HEARTBEAT) and time.monotonic() < deadline:
                time.sleep(0.05)
            [beat] = client.hvals(WORKERS_HEARTBEAT)
            assert b'"concurrency": 2' in beat
            process.send_signal(signal.SIGTERM)
            assert process.wait(30) == 0
        finally:
            if process.poll() is None:  # a failed check must not leave it reconnecting
                process.kill()
                process.wait(30)
        assert client.hlen(WORKERS_HEARTBEAT) == 0
        process.communicate()


@pytest.mark.parametrize("start", range(3))
def test_a_burst_of_stop_signals_ends_the_worker_without_a_traceback(
    tmp_path: Path, start: int
) -> None:
    """SIGINT and SIGTERM as fast as another process can send them. The worker's handler
    stopped it itself (logging, then setting a threading.Event): signals that came
    faster than it finished nested handlers until a RecursionError traceback and an exit
    by the signal (1 of 8 starts at log level ERROR, 2 of 5 in another run; a race, so
    not every start shows it). The first signal stops it, the second exits at once, as
    documented: 0 or 1, with no traceback."""
    with EmbeddedRedis(tmp_path) as url:
        client = connect(url)
        env = {"MCAM_DATA_DIR": str(tmp_path)}
        process = mcam(
            "worker", "--no-devices", "--concurrency", "1", "--log-level", "ERROR", env=env
        )
        with stopped_by_signal_flood(process) as stderr:
            deadline = time.monotonic() + 60
            while not client.hlen(WORKERS_HEARTBEAT) and time.monotonic() < deadline:
                time.sleep(0.05)
        assert process.returncode in (0, 1), stderr
        assert "Traceback" not in stderr[0], stderr


def test_worker_rejects_a_spin_setting_it_cannot_read(tmp_path: Path) -> None:
    process = mcam("worker", env={"MCAM_DATA_DIR": str(tmp_path), "MCAM_ORT_SPIN": "often"})
    _out, err = process.communicate(timeout=60)
    assert process.returncode == 2
    assert "MCAM_ORT_SPIN='often'" in err and "Traceback" not in err


def test_thread_limits_carry_the_spin_setting(monkeypatch: pytest.MonkeyPatch) -> None:
    from models.decoders.learned import ort_spinning, worker_threads
    from service.cli.worker import set_thread_limits

    for name in ("MCAM_WORKER_THREADS", "OMP_NUM_THREADS", "MCAM_ORT_SPIN"):
        monkeypatch.setenv(name, "")  # so that monkeypatch restores what the test changes
        monkeypatch.delenv(name)
    set_thread_limits(3, spin=True)
    assert worker_threads() == 3 and ort_spinning()
    set_thread_limits(1)
    assert worker_threads() == 1 and not ort_spinning()


def test_every_unreadable_setting_is_named_in_one_line(monkeypatch: pytest.MonkeyPatch) -> None:
    from pydantic import ValidationError

    from service.cli.main import settings_problems
    from service.core.config import Settings

    monkeypatch.setenv("MCAM_PORT", "abc")
    monkeypatch.setenv("MCAM_WORKER_THREADS", "0")
    with pytest.raises(ValidationError) as caught:
        Settings()
    line = settings_problems(caught.value)
    assert "\n" not in line
    assert "MCAM_PORT='abc'" in line and "MCAM_WORKER_THREADS='0'" in line


def test_the_settings_and_the_models_read_the_spin_words_alike(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    from models.decoders.learned import SPIN_WORDS, ort_spinning
    from service.core.config import Settings

    for word, spinning in SPIN_WORDS.items():
        monkeypatch.setenv("MCAM_ORT_SPIN", word)
        assert Settings().ort_spin is spinning is ort_spinning(), word


def test_an_unknown_decoder_is_refused_with_one_line(tmp_path: Path) -> None:
    """``--decoder magic --no-devices`` ran: each job child then died at its start with a
    traceback (its warm-up builds that decoder), and every job, whatever decoder it
    named, failed as 'decoder_crashed: the decoding process died'."""
    process = mcam("worker", "--decoder", "magic", "--no-devices",
                   env={"MCAM_DATA_DIR": str(tmp_path)})  # fmt: skip
    _out, err = process.communicate(timeout=60)
    assert process.returncode == 2 and "Traceback" not in err
    assert err.startswith("mcam worker: error: --decoder: unknown decoder 'magic'; choose")


def test_more_threads_than_a_session_can_use_are_refused(tmp_path: Path) -> None:
    """``--threads 100000`` ran: a job's decoding process grew by 4.5 GB in a minute, at
    100 % of a core, and never finished a 64 x 64 frame."""
    process = mcam("worker", "--threads", "100000", env={"MCAM_DATA_DIR": str(tmp_path)})
    _out, err = process.communicate(timeout=60)
    assert process.returncode == 2 and "Traceback" not in err
    assert err.startswith("mcam worker: error: --threads must be at most 256 (")
    assert err.rstrip().endswith("got 100000")


@pytest.mark.parametrize("flag", ["--concurrency", "--stream-processes"])
def test_more_processes_than_a_machine_can_hold_are_refused(tmp_path: Path, flag: str) -> None:
    """``--concurrency 10000000000000000000`` ran: the worker made one job thread object
    after another (each thread then starts a decoding process of about 165 MB) and grew
    by about 150 MB/s until it ran out of memory, ending in a MemoryError traceback.
    ``--stream-processes`` 1e19 ended the worker at start with an OverflowError
    traceback (the pool's barrier), and 2e9 started over a hundred decoding processes
    within 8 s."""
    process = mcam("worker", flag, str(10**19), env={"MCAM_DATA_DIR": str(tmp_path)})
    _out, err = process.communicate(timeout=60)
    assert process.returncode == 2 and "Traceback" not in err
    assert err.startswith(f"mcam worker: error: {flag} must be at most 256 (")
    assert err.rstrip().endswith(f"got {10**19}")


def group_running(pgid: int) -> set[int]:
    """The processes of process group ``pgid`` that run now (zombies left out)."""
    found = set()
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(") ", 1)[1].split()
        except (FileNotFoundError, ProcessLookupError):
            continue
        if fields[0] != "Z" and int(fields[2]) == pgid:
            found.add(int(stat.parent.name))
    return found


@pytest.mark.parametrize("start", range(3))
def test_ctrl_c_as_the_worker_starts_its_children_stops_it_cleanly(
    tmp_path: Path, start: int
) -> None:
    """A terminal's Ctrl-C (SIGINT to the process group) just as the worker starts its
    decode processes reached them while they still started Python: each printed a
    ``Fatal Python error: init_import_site`` or a KeyboardInterrupt traceback. Now the
    worker alone takes it, exits 0 and leaves none of its processes."""
    with EmbeddedRedis(tmp_path):
        clean = {k: v for k, v in os.environ.items() if not k.startswith("MCAM_")}
        process = subprocess.Popen(
            [sys.executable, "-m", "service.cli.main", "worker", "--stream-processes", "2"],
            cwd=REPO, env={**clean, "MCAM_DATA_DIR": str(tmp_path)}, text=True,
            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, start_new_session=True,
        )  # fmt: skip
        try:
            before = "".join(read_until(process, r"running \(", 120))
            os.killpg(process.pid, signal.SIGINT)
            after, _ = process.communicate(timeout=90)
        finally:
            if process.poll() is None:
                os.killpg(process.pid, signal.SIGKILL)
                process.wait(30)
        output = before + after
        assert process.returncode == 0, output
        assert "Traceback" not in output and "Fatal Python error" not in output, output
        wait_gone(group_running(process.pid))
        assert not group_running(process.pid)
