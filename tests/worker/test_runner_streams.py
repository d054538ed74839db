"""Device frame streams through real ``mcam worker`` processes on a real redis-server:
per-device ordering through two workers with a takeover, dead-lettered and repeated
frames, stored compression, a camera that counts from zero again, devices spread over
workers, and an unknown stream decoder."""

from __future__ import annotations

import signal
from collections.abc import Callable
from pathlib import Path

import OpenEXR
import pytest
import redis

from models.formation import SensorFrame
from tests.worker.conftest import OVERFLOW, overflowing_codes, result_files
from worker.deliveries import GROUP
from worker.frame_message import FrameMessage
from worker.lease import Lease
from worker.queue import publish_frame
from worker.redis_keys import DEAD_LETTER_STREAM, events_stream, frame_stream, latest_key
from worker.result_store import RESULTS_DIR


def stored_compression(data_dir: Path, key: str) -> object:
    """The compression named in a stored EXR's header."""
    path = data_dir / RESULTS_DIR / key
    return OpenEXR.File(str(path), header_only=True).header()["compression"]


def frame_events(client: redis.Redis, device: str) -> list[dict[str, str]]:
    return [
        {k.decode(): v.decode() for k, v in fields.items()}
        for _id, fields in client.xrange(events_stream(device))
    ]


def publish(client: redis.Redis, device: str, frame: SensorFrame, sequences: range) -> None:
    for seq in sequences:
        message = FrameMessage(device, seq, seq * 1000, frame.codes, frame.params)
        assert publish_frame(client, message, maxlen=1000) == 0


def test_device_frames_in_order_through_two_workers_with_takeover(
    client: redis.Redis,
    workers,
    data_dir: Path,
    make_frame,
    wait_until: Callable[..., object],
) -> None:
    frame: SensorFrame = make_frame()
    device = "cam-1"
    started = [workers.start(), workers.start()]
    publish(client, device, frame, range(100))
    wait_until(lambda: len(frame_events(client, device)) >= 30, 60, "30 frames")
    owner = wait_until(lambda: Lease(client, "probe", 1000).holder(device), 30, "the lease")
    assert isinstance(owner, str)
    victim = next(p for p in started if f"-{p.pid}-" in owner)
    victim.send_signal(signal.SIGKILL)
    victim.wait(10)
    publish(client, device, frame, range(100, 200))
    wait_until(
        lambda: (e := frame_events(client, device)) and e[-1]["sequence"] == "199",
        90,
        "frame 199",
    )
    events = frame_events(client, device)
    assert [e["type"] for e in events] == ["frame"] * 200
    assert [int(e["sequence"]) for e in events] == list(range(200))
    assert len({e["worker"] for e in events}) == 2
    expected = [e["key"] for e in events]
    assert [key.split("/")[2].split("-")[0] for key in expected] == [
        f"{seq:012d}" for seq in range(200)
    ]
    assert result_files(data_dir) == expected
    assert client.get(latest_key(device)).decode() == expected[-1]
    wait_until(lambda: client.xlen(f"frames:{device}") == 0, 10, "frames acked and deleted")


def test_failing_device_frame_is_dead_lettered_and_order_kept(
    client: redis.Redis, workers, data_dir: Path, make_frame, wait_until
) -> None:
    frame: SensorFrame = make_frame()
    device = "cam-2"
    workers.start()
    publish(client, device, frame, range(2))
    bad = FrameMessage(device, 2, 2000, overflowing_codes(), OVERFLOW)
    publish_frame(client, bad, maxlen=1000)
    publish(client, device, frame, range(3, 5))
    wait_until(lambda: len(frame_events(client, device)) >= 5, 60, "5 events")
    events = frame_events(client, device)
    assert [(e["type"], int(e["sequence"])) for e in events] == [
        ("frame", 0),
        ("frame", 1),
        ("failed", 2),
        ("frame", 3),
        ("frame", 4),
    ]
    assert events[2]["code"] == "output_overflow"
    [(_id, letter)] = client.xrange(DEAD_LETTER_STREAM)
    assert letter[b"device"] == device.encode() and letter[b"sequence"] == b"2"
    assert letter[b"deliveries"] == b"1"  # a bad frame fails the same way every time
    assert len(result_files(data_dir)) == 4


@pytest.mark.parametrize("processes", ["1", "2"])
def test_repeated_sequence_is_not_written_twice(
    client: redis.Redis, workers, data_dir: Path, make_frame, wait_until, processes: str
) -> None:
    """In the worker process and on a decode pool (worker/decode_pool.py) alike."""
    frame: SensorFrame = make_frame()
    device = "cam-3"
    workers.start(MCAM_STREAM_PROCESSES=processes)
    publish(client, device, frame, range(3))
    publish(client, device, frame, range(1, 2))
    wait_until(lambda: len(frame_events(client, device)) >= 4, 60, "4 events")
    types = [(e["type"], int(e["sequence"])) for e in frame_events(client, device)]
    assert types == [("frame", 0), ("frame", 1), ("frame", 2), ("stale", 1)]
    keys = result_files(data_dir)
    assert len(keys) == 3
    # Recording a frame acknowledges and deletes its entry in the same step.
    assert client.xlen(frame_stream(device)) == 0
    assert client.xpending(frame_stream(device), GROUP)["pending"] == 0
    # By default a stream's frames are stored uncompressed (worker.outputs).
    assert {stored_compression(data_dir, key) for key in keys} == {OpenEXR.NO_COMPRESSION}


def test_stream_frames_are_zip_compressed_when_configured(
    client: redis.Redis, workers, data_dir: Path, make_frame, wait_until
) -> None:
    frame: SensorFrame = make_frame()
    device = "cam-zip"
    workers.start(MCAM_STREAM_EXR_COMPRESSION="zip")
    publish(client, device, frame, range(2))
    wait_until(lambda: len(frame_events(client, device)) >= 2, 60, "2 frames")
    keys = result_files(data_dir)
    assert len(keys) == 2
    assert {stored_compression(data_dir, key) for key in keys} == {OpenEXR.ZIP_COMPRESSION}


def test_a_camera_that_counts_from_zero_again_keeps_every_frame(
    client: redis.Redis, workers, data_dir: Path, make_frame, wait_until
) -> None:
    """A restarted camera repeats sequence numbers (its first frame flagged DISCONT):
    each frame gets a file of its own, and each event points at its own frame."""
    frame: SensorFrame = make_frame()
    device = "cam-restart"
    workers.start()
    publish(client, device, frame, range(3))
    for seq in range(2):
        message = FrameMessage(device, seq, seq * 1000, frame.codes, frame.params, seq == 0)
        assert publish_frame(client, message, maxlen=1000) == 0
    wait_until(lambda: len(frame_events(client, device)) >= 5, 60, "5 frames")
    events = frame_events(client, device)
    assert [int(e["sequence"]) for e in events] == [0, 1, 2, 0, 1]
    keys = [e["key"] for e in events]
    assert len(set(keys)) == 5 and sorted(result_files(data_dir)) == sorted(keys)


def test_devices_spread_over_workers(
    client: redis.Redis, workers, data_dir: Path, make_frame, wait_until
) -> None:
    frame: SensorFrame = make_frame()
    devices = ["cam-a", "cam-b"]
    workers.start()
    for device in devices:
        publish(client, device, frame, range(2))
    lease = Lease(client, "probe", 1000)
    wait_until(lambda: all(lease.holder(d) for d in devices), 60, "both devices owned")
    workers.start()
    wait_until(lambda: len({lease.holder(d) for d in devices}) == 2, 60, "one device per worker")
    for device in devices:
        publish(client, device, frame, range(2, 6))
    for device in devices:
        wait_until(
            lambda d=device: (
                [int(e["sequence"]) for e in frame_events(client, d)] == list(range(6))
            ),
            60,
            f"frames 0..5 of {device} in order",
        )
    assert len(result_files(data_dir)) == 12


def test_an_unknown_stream_decoder_stops_the_worker_at_start(workers) -> None:
    """Warming the stream decoder up front turns a bad MCAM_DEFAULT_DECODER into a
    one-line error at start, not a dead device thread at the first frame."""
    process = workers.start("--decoder", "nope")
    output = process.communicate(timeout=60)[0].decode()
    assert process.returncode != 0
    assert "unknown decoder" in output and "nope" in output
    assert "Traceback" not in output
