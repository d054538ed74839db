"""``mcam serve`` as a real process: embedded Redis + worker + API, then a clean stop."""

from __future__ import annotations

import io
import json
import os
import queue
import re
import signal
import stat
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import httpx
import numpy as np
import pytest
import redis

from models.formation import SensorParams, simulate
from service.cli.main import build_parser, main
from service.cli.serve import WorkerSupervisor
from tests.service.conftest import free_port
from worker.embedded_redis import EmbeddedRedis, connect
from worker.job_store import JobStore
from worker.jobs import JobState
from worker.redis_keys import DEVICES_SET, WORKERS_HEARTBEAT

REPO = Path(__file__).resolve().parents[3]


def read_until(process: subprocess.Popen[str], pattern: str, timeout_s: float) -> list[str]:
    """stdout lines up to the first one matching ``pattern``; fails once ``timeout_s``
    has passed, or when the output ends first. A thread reads the lines (it stops after
    the match), so a process that prints nothing cannot hold the wait past its deadline
    (``readline`` here blocked until the process wrote or exited)."""
    stdout = process.stdout
    assert stdout is not None
    arrived: queue.Queue[str | None] = queue.Queue()

    def read() -> None:
        for line in iter(stdout.readline, ""):
            arrived.put(line)
            if re.search(pattern, line):
                return
        arrived.put(None)  # the output ended: the process exited

    threading.Thread(target=read, daemon=True).start()
    deadline = time.monotonic() + timeout_s
    lines: list[str] = []
    while True:
        try:
            line = arrived.get(timeout=max(0.0, deadline - time.monotonic()))
        except queue.Empty:
            pytest.fail(f"no {pattern!r} within {timeout_s}s: {''.join(lines)}")
        if line is None:
            pytest.fail(f"mcam serve exited ({process.poll()}): {''.join(lines)}")
        lines.append(line)
        if re.search(pattern, line):
            return lines


def test_read_until_gives_up_at_its_deadline_on_a_silent_process() -> None:
    silent = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(20)"],
                              stdout=subprocess.PIPE, text=True)
    try:
        with pytest.raises(pytest.fail.Exception, match="no 'ready' within 0.5s"):
            read_until(silent, "ready", 0.5)
    finally:
        silent.kill()
        silent.wait()


def wait_ready(base: str, timeout_s: float = 60.0) -> None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        try:
            if httpx.get(f"{base}/health/ready", timeout=5).status_code == 200:
                return
        except httpx.TransportError:
            pass
        time.sleep(0.2)
    pytest.fail("the service never became ready")


def npy_frame() -> tuple[bytes, SensorParams]:
    y, x = np.mgrid[0:64, 0:64] / 64
    frame = simulate(0.2 + 6 * x * y, SensorParams(encoding="modulo", bits=8))
    buffer = io.BytesIO()
    np.save(buffer, frame.codes)
    return buffer.getvalue(), frame.params


def worker_pids(client: redis.Redis) -> set[int]:
    """Pids of the workers that have a heartbeat."""
    return {json.loads(beat)["pid"] for beat in client.hvals(WORKERS_HEARTBEAT)}


@contextmanager
def serving(
    tmp_path: Path, *flags: str, settings: dict[str, str] | None = None
) -> Iterator[tuple[subprocess.Popen[str], Path, int]]:
    """``mcam serve`` on a free port with its data dir under ``tmp_path``: the process,
    the data dir and the port; killed at the end if it is still running. It leads its
    own process group (as a terminal's foreground job does), its stderr goes to
    ``tmp_path / "stderr"``, and ``settings`` (``MCAM_*``) replace the ones below.

    Each worker decodes device frames in its own process (``MCAM_STREAM_PROCESSES=1``):
    these tests stream from no device, and the default pool (one process per core, each
    importing and warming up its decoder, tested in tests/worker/test_decode_pool.py)
    took seconds of both cores at each worker's start and held up each stop. An open
    request (an event stream) holds a stop for 0.5 s, not the default 5 s."""
    data_dir = tmp_path / "data"
    port = free_port()
    env = {k: v for k, v in os.environ.items() if not k.startswith("MCAM_")}
    env.update({
        "MCAM_DATA_DIR": str(data_dir), "MCAM_HEARTBEAT_S": "0.5", "MCAM_STREAM_PROCESSES": "1",
        "MCAM_HTTP_SHUTDOWN_GRACE_S": "0.5", **(settings or {}),
    })  # fmt: skip
    process = subprocess.Popen(
        [sys.executable, "-m", "service.cli.main", "serve", "--host", "127.0.0.1",
         "--port", str(port), *flags],
        cwd=tmp_path,
        env={**env, "PYTHONPATH": str(REPO)},
        stdout=subprocess.PIPE,
        stderr=(tmp_path / "stderr").open("w"),
        text=True,
        start_new_session=True,
    )  # fmt: skip
    try:
        yield process, data_dir, port
    finally:
        if process.poll() is None:
            process.kill()
            process.wait()


def reconstruct_itoh(base: str, key: str) -> None:
    """One frame through the API, waited for; it must succeed."""
    data, params = npy_frame()
    reply = httpx.post(
        f"{base}/v1/reconstructions",
        files={"file": ("frame.npy", data, "application/octet-stream")},
        data={"encoding": params.encoding, "bits": str(params.bits), "decoder": "itoh"},
        headers={"Authorization": f"Bearer {key}", "Prefer": "wait=30"},
        timeout=60,
    )
    assert reply.status_code == 200, reply.text
    assert reply.json()["state"] == "succeeded"


def test_serve_runs_everything_restarts_a_dead_worker_and_stops_cleanly(tmp_path: Path) -> None:
    with serving(tmp_path) as (process, data_dir, port):
        lines = read_until(process, r"^use it as: Authorization: Bearer ", 90)
        banner = "".join(lines)
        assert f"http://127.0.0.1:{port}/" in banner
        key = lines[-1].split("Bearer ", 1)[1].strip()
        key_file = data_dir / "api_keys"
        assert key_file.read_text().strip() == key
        assert stat.S_IMODE(key_file.stat().st_mode) == 0o600
        base = f"http://127.0.0.1:{port}"
        wait_ready(base)
        reconstruct_itoh(base, key)
        redis_socket = EmbeddedRedis(data_dir).socket
        client = connect(f"unix://{redis_socket}")
        [first_pid] = worker_pids(client)
        os.kill(first_pid, signal.SIGKILL)
        deadline = time.monotonic() + 60
        while not worker_pids(client) - {first_pid} and time.monotonic() < deadline:
            time.sleep(0.1)
        [worker_pid] = worker_pids(client) - {first_pid}
        slow = submit_slow_job(base, key)
        deadline = time.monotonic() + 60
        while JobStore(client).load(slow).state is not JobState.RUNNING:
            assert time.monotonic() < deadline, "the slow job never started"
            time.sleep(0.1)
        process.send_signal(signal.SIGTERM)
        assert process.wait(90) == 0
        assert not redis_socket.exists()
        with pytest.raises(ProcessLookupError):
            os.kill(worker_pid, 0)
    # The restarted worker finished the job in hand (it used to get a second SIGTERM
    # when serve's restart thread ended, and dropped it).
    restarted = EmbeddedRedis(data_dir)
    restarted.start()
    try:
        assert JobStore(connect(restarted.url)).load(slow).state is JobState.SUCCEEDED
    finally:
        restarted.stop()


def submit_slow_job(base: str, key: str) -> str:
    """Graph cuts on 384 x 384 random codes (seconds); its job id."""
    buffer = io.BytesIO()
    np.save(buffer, np.random.default_rng(0).integers(0, 256, (384, 384)).astype(np.uint8))
    reply = httpx.post(
        f"{base}/v1/reconstructions",
        files={"file": ("frame.npy", buffer.getvalue(), "application/octet-stream")},
        data={"encoding": "modulo", "bits": "8", "decoder": "graphcut"},
        headers={"Authorization": f"Bearer {key}"},
        timeout=60,
    )
    assert reply.status_code == 202, reply.text
    return str(reply.json()["id"])


def test_serve_runs_as_many_workers_as_asked_and_stops_them_all(tmp_path: Path) -> None:
    with serving(tmp_path, "--workers", "2", "--threads", "1") as (process, data_dir, port):
        lines = read_until(process, r"^use it as: Authorization: Bearer ", 90)
        key = lines[-1].split("Bearer ", 1)[1].strip()
        base = f"http://127.0.0.1:{port}"
        wait_ready(base)
        client = connect(f"unix://{EmbeddedRedis(data_dir).socket}")
        deadline = time.monotonic() + 60
        while len(worker_pids(client)) < 2 and time.monotonic() < deadline:
            time.sleep(0.1)
        pids = worker_pids(client)
        assert len(pids) == 2
        reconstruct_itoh(base, key)
        process.send_signal(signal.SIGTERM)
        assert process.wait(60) == 0
        for pid in pids:
            with pytest.raises(ProcessLookupError):
                os.kill(pid, 0)


@pytest.mark.parametrize("flag", ["--workers", "--concurrency", "--threads"])
@pytest.mark.parametrize("count", ["0", "-1", "two"])
def test_a_worker_count_below_one_is_refused_with_one_line(
    flag: str, count: str, capsys: pytest.CaptureFixture[str]
) -> None:
    """Refused before anything starts (a worker given --concurrency 0 used to exit at
    once and be restarted for ever)."""
    with pytest.raises(SystemExit) as stopped:
        main(["serve", flag, count])
    assert stopped.value.code == 2
    err = capsys.readouterr().err
    assert flag in err and "whole number >= 1" in err and "Traceback" not in err


def test_a_worker_that_keeps_dying_is_restarted_ever_more_slowly(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A worker that dies 1.2 s after each start (alive at the supervisor's first poll)
    is restarted after 1, 2, then 4 s: the wait starts again only after a worker has
    stayed up for HEALTHY_AFTER_S (it used to go 1, 2, 1, 2 s)."""
    script = tmp_path / "dies.py"
    script.write_text("import time\ntime.sleep(1.2)\n")
    supervisor = WorkerSupervisor([sys.executable, str(script)], "unused", "unused").start()
    deadline = time.monotonic() + 40
    waits: list[str] = []
    while len(waits) < 3 and time.monotonic() < deadline:
        time.sleep(0.2)
        waits += re.findall(r"restarting in (\d+) s", capsys.readouterr().err)
    supervisor.terminate()
    supervisor.wait()
    assert waits[:3] == ["1", "2", "4"]


SIGNAL_RECORDER = """
import signal, sys, time
from pathlib import Path
log, release = Path(sys.argv[1]), Path(sys.argv[2])
stop_at = None
def on_term(*_):
    global stop_at
    with log.open("a") as f:
        f.write("TERM\\n")
    stop_at = stop_at or time.monotonic() + 60.0
signal.signal(signal.SIGTERM, on_term)
with log.open("a") as f:
    f.write("start\\n")
while stop_at is None or (time.monotonic() < stop_at and not release.exists()):
    time.sleep(0.02)
"""


def test_a_restarted_worker_gets_one_sigterm_and_its_watch_outlives_it(tmp_path: Path) -> None:
    """PR_SET_PDEATHSIG follows the thread that forked: the thread that restarted a worker
    must stay until that worker exits, or the worker gets a second SIGTERM (which makes
    a real worker drop the job in hand)."""
    script, log = tmp_path / "recorder.py", tmp_path / "signals.log"
    release = tmp_path / "release"  # the worker exits after SIGTERM once this exists
    script.write_text(SIGNAL_RECORDER)
    supervisor = WorkerSupervisor([sys.executable, str(script), str(log), str(release)],
                                  "unused", "unused")
    supervisor.start()

    def starts() -> int:
        return log.read_text().count("start") if log.exists() else 0

    deadline = time.monotonic() + 30
    while starts() < 1 and time.monotonic() < deadline:
        time.sleep(0.02)
    assert supervisor.process is not None
    supervisor.process.kill()
    while starts() < 2 and time.monotonic() < deadline:
        time.sleep(0.02)
    assert starts() == 2, "the supervisor did not restart the worker"
    supervisor.terminate()
    time.sleep(0.3)
    assert supervisor._thread.is_alive()  # the worker still runs: its watch must too
    release.touch()
    supervisor.wait()
    assert log.read_text().count("TERM") == 1
    assert supervisor.process.returncode == 0


def test_an_open_event_stream_does_not_keep_serve_from_stopping(tmp_path: Path) -> None:
    """uvicorn waited for every connection to close: with one client on a device's
    events, SIGTERM left the server half-stopped (no new connections, worker and Redis
    still running) for as long as the client stayed."""
    with serving(tmp_path) as (process, data_dir, port):
        lines = read_until(process, r"^use it as: Authorization: Bearer ", 90)
        key = lines[-1].split("Bearer ", 1)[1].strip()
        base = f"http://127.0.0.1:{port}"
        wait_ready(base)
        connect(f"unix://{EmbeddedRedis(data_dir).socket}").sadd(DEVICES_SET, "cam1")
        opened = threading.Event()

        def listen() -> None:
            with httpx.stream("GET", f"{base}/v1/devices/cam1/events",
                              headers={"Authorization": f"Bearer {key}"}, timeout=120) as reply:
                assert reply.status_code == 200
                opened.set()
                try:
                    for _ in reply.iter_bytes():
                        pass
                except httpx.HTTPError:
                    pass  # the stopping server cut the stream: what this test wants

        listener = threading.Thread(target=listen, daemon=True)
        listener.start()
        assert opened.wait(30)
        process.send_signal(signal.SIGTERM)
        assert process.wait(60) == 0  # it hung until the client left


def descendants(pid: int) -> set[int]:
    """The processes ``pid`` started, and theirs, now (Linux: /proc's children lists)."""
    found: set[int] = set()
    for children in Path(f"/proc/{pid}/task").glob("*/children"):
        for child in map(int, children.read_text().split()):
            found |= {child} | descendants(child)
    return found


def running(pid: int) -> bool:
    """Whether process ``pid`` exists and is no zombie."""
    try:
        return not Path(f"/proc/{pid}/stat").read_text().rsplit(") ", 1)[1].startswith("Z")
    except FileNotFoundError:
        return False


def wait_gone(pids: set[int], timeout_s: float = 30.0) -> None:
    """Wait until none of ``pids`` runs; fail at the deadline."""
    deadline = time.monotonic() + timeout_s
    while left := {pid for pid in pids if running(pid)}:
        assert time.monotonic() < deadline, f"left running after the stop: {left}"
        time.sleep(0.1)


def wait_for_stderr(tmp_path: Path, text: str, timeout_s: float = 60.0) -> None:
    """Wait until ``serving``'s stderr holds ``text``; fail at the deadline."""
    deadline = time.monotonic() + timeout_s
    while text not in (tmp_path / "stderr").read_text():
        assert time.monotonic() < deadline, f"no {text!r} on stderr within {timeout_s} s"
        time.sleep(0.1)


def assert_stopped_cleanly(
    process: subprocess.Popen[str], tmp_path: Path, started: set[int]
) -> None:
    """serve exited 0 with no traceback on stderr, and left none of its processes."""
    assert process.wait(90) == 0
    stderr = (tmp_path / "stderr").read_text()
    assert "Traceback" not in stderr and "CancelledError" not in stderr, stderr
    wait_gone(started)


@pytest.mark.parametrize("start", range(3))
def test_ctrl_c_stops_serve_cleanly(tmp_path: Path, start: int) -> None:
    """A terminal's Ctrl-C (SIGINT to the foreground process group) stops serve with
    exit 0, no traceback and no process left; several starts, as a stop races the
    lifespan's shutdown."""
    with serving(tmp_path) as (process, _, port):
        read_until(process, r"^use it as: Authorization: Bearer ", 90)
        wait_ready(f"http://127.0.0.1:{port}")
        started = descendants(process.pid)
        os.killpg(process.pid, signal.SIGINT)
        assert_stopped_cleanly(process, tmp_path, started)


@pytest.mark.parametrize("presses", [1, 2])
def test_ctrl_c_with_an_open_event_stream_stops_serve_cleanly(
    tmp_path: Path, presses: int
) -> None:
    """A request still open when serve stops (a viewer's event stream) is cancelled past
    the grace period, or at once on a second Ctrl-C (uvicorn asks for one while it
    waits): each cancelled request logged a CancelledError traceback, and a second
    Ctrl-C skipped the app's shutdown and raised KeyboardInterrupt in asyncio, so stderr
    also showed a KeyboardInterrupt and a CancelledError out of the app's lifespan.
    (With two presses the grace period is long: only the second one ends it.)"""
    grace_s = "0.5" if presses == 1 else "300"
    with serving(tmp_path, settings={"MCAM_HTTP_SHUTDOWN_GRACE_S": grace_s}) as (
        process, data_dir, port
    ):
        lines = read_until(process, r"^use it as: Authorization: Bearer ", 90)
        key = lines[-1].split("Bearer ", 1)[1].strip()
        base = f"http://127.0.0.1:{port}"
        wait_ready(base)
        connect(f"unix://{EmbeddedRedis(data_dir).socket}").sadd(DEVICES_SET, "cam1")
        with httpx.stream("GET", f"{base}/v1/devices/cam1/events", timeout=120,
                          headers={"Authorization": f"Bearer {key}"}) as reply:
            assert reply.status_code == 200
            started = descendants(process.pid)
            os.killpg(process.pid, signal.SIGINT)
            if presses == 2:
                wait_for_stderr(tmp_path, "Waiting for connections to close")
                os.killpg(process.pid, signal.SIGINT)
            assert_stopped_cleanly(process, tmp_path, started)


@pytest.mark.parametrize("flag", ["--threads", "--concurrency", "--workers"])
def test_more_than_a_worker_takes_is_refused_with_one_line(
    flag: str, capsys: pytest.CaptureFixture[str]
) -> None:
    """``--threads 100000`` was passed on to workers (whose decoding processes then grew
    without end), and so was ``--concurrency 100000`` (the worker grew by a job thread
    and its process after another until memory ran out); refused at once, as the worker
    now refuses them. ``--workers 10000000000000000000`` started worker after worker
    (107 in 20 s, 7.5 GB), and SIGTERM did not stop it. (The arguments are only parsed:
    a regression must not start a service.)"""
    with pytest.raises(SystemExit) as stopped:
        build_parser("serve").parse_args(["serve", flag, "100000"])
    assert stopped.value.code == 2
    err = capsys.readouterr().err
    assert f"argument {flag}: must be at most 256 (" in err and "got 100000" in err
