"""The stream decode pool: real processes, results equal to the worker's own decoder,
taken in stream order, errors and dead processes handled."""

from __future__ import annotations

import contextlib
import math
import os
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from models.errors import InvalidInputError, McamError
from models.formation import SensorParams
from models.scenes import synthetic_val256_frame
from worker import decode_pool as decode_pool_module
from worker.decode_pool import DecodePool
from worker.device_state import DeviceState, make_frame_decoder
from worker.frame_message import FrameMessage

DEVICE = "cam-pool"
REPO = Path(__file__).resolve().parents[2]


def messages(count: int, encoding: str = "mantissa") -> list[FrameMessage]:
    """``count`` distinct 64x64 frames of a seeded synthetic scene, as one stream."""
    return [
        FrameMessage(DEVICE, seq, seq * 1000, frame.codes[:64, :64], frame.params)
        for seq, frame in enumerate(
            synthetic_val256_frame(encoding, 128, seed) for seed in range(count)
        )
    ]


def entries(stream: list[FrameMessage]) -> list[tuple[str, FrameMessage]]:
    return [(f"{m.sequence}-0", m) for m in stream]


@pytest.fixture(scope="module")
def pool() -> Iterator[DecodePool]:
    decode_pool = DecodePool("auto-fast", 2)
    yield decode_pool
    decode_pool.close()


@pytest.fixture
def pooled(monkeypatch: pytest.MonkeyPatch) -> None:
    """Every frame goes to the pool, however cheap."""
    monkeypatch.setattr(decode_pool_module, "LOCAL_BELOW_MS", 0.0)


@pytest.mark.parametrize("cheap_below_ms", [0.0, math.inf], ids=["pool", "worker"])
def test_results_in_order_equal_the_worker_s_own_decoder(
    pool: DecodePool, monkeypatch: pytest.MonkeyPatch, cheap_below_ms: float
) -> None:
    monkeypatch.setattr(decode_pool_module, "LOCAL_BELOW_MS", cheap_below_ms)
    device = f"cam-{cheap_below_ms}"
    stream = entries(messages(6))
    pool.prefetch(device, stream)
    own = make_frame_decoder("independent", "auto-fast")
    for entry_id, message in stream:
        frame = pool.result(device, entry_id, message)
        expected = own(DeviceState(DEVICE), message)
        assert frame.winding.dtype == np.int64
        np.testing.assert_array_equal(frame.winding, expected.winding)
        assert frame.info == expected.info
        assert frame.timings_ns["decode"] > 0
    assert pool.local(device) == (cheap_below_ms > 0)


def test_cheap_frames_are_decoded_in_the_worker_and_busy_ones_go_back_to_the_pool(
    pool: DecodePool,
) -> None:
    device = "cam-dark"
    dark = FrameMessage(device, 0, 0, np.zeros((64, 64), np.uint8), SensorParams(bits=8))
    assert not pool.local(device)
    pool.result(device, "0-0", dark)
    assert pool.local(device)
    pool.prefetch(device, [("1-0", dark)])
    assert not pool._pending.get(device)
    busy = synthetic_val256_frame("mantissa", 256, 1)
    for sequence in range(1, 4):
        message = FrameMessage(device, sequence, 0, busy.codes, busy.params)
        pool.result(device, f"{sequence}-0", message)
    assert not pool.local(device)
    pool.prefetch(device, [("4-0", message)])
    assert list(pool._pending[device]) == ["4-0"]
    pool.discard(device)


def test_a_frame_not_prefetched_or_dropped_from_a_later_batch_is_decoded_on_demand(
    pool: DecodePool, pooled: None
) -> None:
    first, second, third = entries(messages(3))
    pool.prefetch(DEVICE, [first, second])
    pool.prefetch(DEVICE, [third])
    for entry_id, message in (first, second, third):
        assert pool.result(DEVICE, entry_id, message).winding.shape == (64, 64)
    pool.discard(DEVICE)
    assert pool.result("elsewhere", *first).winding.shape == (64, 64)


def test_a_decoding_error_is_raised_as_the_decoder_raised_it(
    pool: DecodePool, pooled: None
) -> None:
    codes = np.full((8, 8), 300, np.uint16)
    bad = FrameMessage(DEVICE, 99, 0, codes, SensorParams(encoding="modulo", bits=8))
    with pytest.raises(InvalidInputError) as own:
        make_frame_decoder("independent", "auto-fast")(DeviceState(DEVICE), bad)
    pool.prefetch(DEVICE, [("99-0", bad)])
    with pytest.raises(InvalidInputError) as pooled:
        pool.result(DEVICE, "99-0", bad)
    assert pooled.value.message == own.value.message


def test_wait_ready_names_every_process_once_warm() -> None:
    decode_pool = DecodePool("itoh", 2)
    try:
        pids = decode_pool.wait_ready()
        assert len(pids) == 2 and pids == set(decode_pool._executor._processes)
    finally:
        decode_pool.close()


def test_a_process_that_dies_mid_frame_fails_that_frame_and_a_new_pool_takes_the_rest(
    pooled: None,
) -> None:
    frames = [synthetic_val256_frame("mantissa", 256, seed) for seed in range(3)]
    stream = entries([FrameMessage(DEVICE, k, k, f.codes, f.params) for k, f in enumerate(frames)])
    decode_pool = DecodePool("auto-fast", 2)
    try:
        old = decode_pool.wait_ready()
        decode_pool.prefetch(DEVICE, stream)
        for pid in old:
            os.kill(pid, signal.SIGKILL)
        with pytest.raises(RuntimeError, match="decode process died while decoding frame 0"):
            decode_pool.result(DEVICE, *stream[0])
        own = make_frame_decoder("independent", "auto-fast")
        for entry_id, message in stream:
            frame = decode_pool.result(DEVICE, entry_id, message)
            np.testing.assert_array_equal(frame.winding, own(DeviceState(DEVICE), message).winding)
        assert not decode_pool.wait_ready() & old
    finally:
        decode_pool.close()


def test_when_one_process_dies_its_survivor_is_ended_with_the_broken_pool(
    pooled: None,
) -> None:
    """One of two processes killed while both decode large frames: the survivor, which
    ignores SIGTERM and may be blocked writing its result to the dead pool's pipe, is
    killed with the pool (it outlived close() and hung the worker's exit)."""
    frame = synthetic_val256_frame("modulo", 1024, 0)
    stream = entries([FrameMessage(DEVICE, k, k, frame.codes, frame.params) for k in range(4)])
    decode_pool = DecodePool("itoh", 2)
    try:
        old = decode_pool.wait_ready()
        decode_pool.prefetch(DEVICE, stream)
        os.kill(min(old), signal.SIGKILL)
        for entry_id, message in stream:
            with contextlib.suppress(RuntimeError):
                decode_pool.result(DEVICE, entry_id, message)
        deadline = time.monotonic() + 10
        while any(alive(pid) for pid in old) and time.monotonic() < deadline:
            time.sleep(0.05)
        assert not any(alive(pid) for pid in old)
    finally:
        decode_pool.close()


def test_a_pool_found_broken_when_a_batch_arrives_is_replaced(pooled: None) -> None:
    stream = entries(messages(3, "modulo"))
    decode_pool = DecodePool("itoh", 2)
    try:
        old = decode_pool.wait_ready()
        for pid in old:
            os.kill(pid, signal.SIGKILL)
        while not decode_pool._executor._broken:
            time.sleep(0.01)
        decode_pool.prefetch(DEVICE, stream)
        own = make_frame_decoder("independent", "itoh")
        for entry_id, message in stream:
            frame = decode_pool.result(DEVICE, entry_id, message)
            np.testing.assert_array_equal(frame.winding, own(DeviceState(DEVICE), message).winding)
    finally:
        decode_pool.close()


def test_a_pool_of_fewer_than_two_processes_is_refused() -> None:
    with pytest.raises(McamError, match="at least 2 processes"):
        DecodePool("itoh", 1)


def test_pool_processes_exit_when_their_worker_is_killed(tmp_path: Path) -> None:
    """A worker killed outright cannot shut its pool down: the processes leave by
    themselves instead of waiting for work for ever."""
    script = (
        "from worker.decode_pool import DecodePool\n"
        "pool = DecodePool('itoh', 2)\n"
        "print(' '.join(map(str, pool.wait_ready())), flush=True)\n"
        "import time; time.sleep(600)\n"
    )
    worker = subprocess.Popen(
        [sys.executable, "-c", script], cwd=REPO, stdout=subprocess.PIPE, text=True
    )
    try:
        assert worker.stdout is not None
        pids = [int(pid) for pid in worker.stdout.readline().split()]
        assert len(pids) == 2 and all(alive(pid) for pid in pids)
    finally:
        worker.kill()
        worker.wait(10)
    deadline = time.monotonic() + 30
    while any(alive(pid) for pid in pids) and time.monotonic() < deadline:
        time.sleep(0.1)
    assert not any(alive(pid) for pid in pids)


def alive(pid: int) -> bool:
    """Whether process ``pid`` runs (a zombie, dead but not yet reaped, does not)."""
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except FileNotFoundError:
        return False
    return state != "Z"
