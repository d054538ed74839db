"""Tests of worker/device_consumer.py: a device stream's frames, each committed or
dead-lettered once, against a real Redis."""

from __future__ import annotations

import contextlib
import threading
import time
from pathlib import Path

import pytest
import redis

from models.decoders import learned
from models.formation import SensorParams
from tests.worker.conftest import break_model_file, ramp_frame, residue_frame
from worker.decode_pool import DecodePool
from worker.deliveries import GROUP
from worker.device_consumer import DeviceConsumer, LeaseLost
from worker.device_registry import forget_device
from worker.device_state import DecodedFrame, DeviceState, make_frame_decoder
from worker.frame_message import FrameMessage
from worker.metrics import read_metrics
from worker.queue import ensure_group, publish_frame
from worker.recordings import load_recording, start_recording
from worker.redis_keys import (
    DEAD_LETTER_STREAM,
    DEVICES_SET,
    events_stream,
    frame_stream,
    lease_key,
)
from worker.result_store import RESULTS_DIR, ResultStore


def device_worker(
    client: redis.Redis, tmp_path: Path, owner: str = "w1", lease_ms: int = 5000
) -> DeviceConsumer:
    """A worker's device side, decoding with itoh, storing under ``tmp_path``."""
    store = ResultStore(tmp_path / RESULTS_DIR, retention_s=3600)
    return DeviceConsumer(
        client, store, owner=owner, lease_ms=lease_ms, max_deliveries=3,
        decode=make_frame_decoder("independent", "itoh"), stop=threading.Event(),
    )  # fmt: skip


@pytest.fixture
def consumer(client: redis.Redis, tmp_path: Path) -> DeviceConsumer:
    return device_worker(client, tmp_path)


def frame(device: str, sequence: int) -> FrameMessage:
    sensor = ramp_frame(size=16)
    return FrameMessage(device, sequence, sequence * 1000, sensor.codes, sensor.params)


def dead_letters(client: redis.Redis) -> list[dict[bytes, bytes]]:
    return [fields for _, fields in client.xrange(DEAD_LETTER_STREAM)]


@pytest.mark.parametrize("seq", [b"\xff", "²".encode()])
def test_an_entry_whose_sequence_does_not_parse_is_dead_lettered_and_the_rest_flow(
    client: redis.Redis, consumer: DeviceConsumer, seq: bytes
) -> None:
    """A seq that is not UTF-8, or a digit ``int`` refuses: the entry goes to the dead
    letters with its reason, and the device's next frame and another device's frame
    are decoded (it used to raise out of every poll, stalling every device after it)."""
    fields = frame("a", 0).to_fields()
    fields["seq"] = seq
    client.sadd(DEVICES_SET, "a")
    client.xadd(frame_stream("a"), fields)
    publish_frame(client, frame("a", 1), maxlen=10)
    publish_frame(client, frame("b", 0), maxlen=10)
    consumer.poll()
    (letter,) = dead_letters(client)
    assert letter[b"stream"] == frame_stream("a").encode()
    assert client.xlen(frame_stream("a")) == 0 and client.xlen(frame_stream("b")) == 0
    assert consumer.states["a"].last_sequence == 1


def test_a_frame_naming_another_device_is_dead_lettered_not_recorded_there(
    client: redis.Redis, consumer: DeviceConsumer
) -> None:
    """The stream is the device's identity: a frame on a's stream that names b does not
    join b's recording."""
    client.sadd(DEVICES_SET, "a", "b")
    start_recording(client, "b", decoder="itoh", options={"mode": "temporal"}, max_frames=10)
    client.xadd(frame_stream("a"), frame("b", 0).to_fields())
    consumer.poll()
    (letter,) = dead_letters(client)
    assert b"names device 'b' but arrived on 'a'" in letter[b"message"]
    assert load_recording(client, "b").frames == 0


def test_a_device_forgotten_from_the_registry_is_let_go(
    client: redis.Redis, consumer: DeviceConsumer
) -> None:
    publish_frame(client, frame("a", 0), maxlen=10)
    publish_frame(client, frame("b", 0), maxlen=10)
    consumer.poll()
    assert set(consumer.states) == {"a", "b"}
    forget_device(client, "a", silent_after_s=0.0)
    consumer.poll()
    assert set(consumer.states) == {"b"}


def test_a_device_let_go_leaves_nothing_in_the_decode_pool(
    client: redis.Redis, tmp_path: Path
) -> None:
    """The pool kept each device's average decode time for good: a worker that saw
    cameras come and go for weeks kept one per camera ever owned."""
    pool = DecodePool("itoh", 2)
    try:
        consumer = DeviceConsumer(
            client, ResultStore(tmp_path / RESULTS_DIR, retention_s=3600), owner="w1",
            lease_ms=5000, max_deliveries=3, decode=pool, stop=threading.Event(),
        )  # fmt: skip
        for device in ("a", "b"):
            publish_frame(client, frame(device, 0), maxlen=10)
        consumer.poll()
        assert set(pool._cost_ms) == {"a", "b"}
        forget_device(client, "a", silent_after_s=0.0)
        consumer.poll()
        assert set(pool._cost_ms) == {"b"}
    finally:
        pool.close()


def test_a_take_over_deletes_the_earlier_owners_consumers(
    client: redis.Redis, consumer: DeviceConsumer
) -> None:
    """Each worker that ever owned a device left its consumer in the device stream's
    group: a camera streaming for weeks through worker restarts kept one per start. The
    earlier owner's frame pending there is decoded by the new owner."""
    publish_frame(client, frame("a", 0), maxlen=10)
    ensure_group(client, frame_stream("a"))
    client.xgroup_createconsumer(frame_stream("a"), GROUP, "w0-idle")
    client.xreadgroup(GROUP, "w0-busy", {frame_stream("a"): ">"})
    publish_frame(client, frame("a", 1), maxlen=10)
    consumer.poll()
    names = {row["name"].decode() for row in client.xinfo_consumers(frame_stream("a"), GROUP)}
    assert names == {"w1"}
    consumer.poll()  # the new frame, after the one taken over
    assert consumer.states["a"].last_sequence == 1 and client.xlen(frame_stream("a")) == 0


def test_entries_a_lapsed_owner_read_after_the_take_over_are_decoded_by_the_new_one(
    client: redis.Redis, tmp_path: Path
) -> None:
    """Worker A's lease lapses (a pause), B takes the device over with nothing pending,
    then A, waking, reads frames 1 and 2 into its own pending list (its commit would fail:
    it no longer holds the lease). B takes them over before new entries and decodes
    them in order; they used to stay pending at A, and a later owner acked them unread.
    A's lease lapses once A has committed frame 0 (a lease short enough to lapse by
    itself could lapse before that commit on a loaded machine: B then did frame 0)."""
    a, b = device_worker(client, tmp_path, "A"), device_worker(client, tmp_path, "B")
    publish_frame(client, frame("cam", 0), maxlen=10)
    a.poll()
    client.delete(lease_key("cam"))  # A's lease lapses
    b.poll()
    assert "cam" in b.states
    publish_frame(client, frame("cam", 1), maxlen=10)
    publish_frame(client, frame("cam", 2), maxlen=10)
    assert len(a._consumers["cam"].read_new(block_ms=None, count=10)) == 2
    publish_frame(client, frame("cam", 3), maxlen=10)
    while b.poll():
        pass
    events = [(e[b"sequence"], e[b"worker"]) for _, e in client.xrange(events_stream("cam"))]
    assert events == [(b"0", b"A"), (b"1", b"B"), (b"2", b"B"), (b"3", b"B")]
    assert client.xpending(frame_stream("cam"), "workers")["pending"] == 0


def test_an_owner_that_lost_the_lease_mid_frame_leaves_its_successors_file(
    client: redis.Redis, tmp_path: Path
) -> None:
    """A decodes frame 0 and pauses past its lease before committing; B takes over and
    commits frame 0. A's late write must not replace the file B's event points at (A
    writes zip-compressed, B uncompressed, so the bytes tell them apart)."""
    a = device_worker(client, tmp_path, "A", 100)
    a.exr_options = {"exr_compression": "zip"}
    b = device_worker(client, tmp_path, "B")
    publish_frame(client, frame("cam", 0), maxlen=10)
    client.sadd(DEVICES_SET, "cam")
    assert a._hold("cam")
    [delivery] = a._consumers["cam"].read_new(block_ms=None, count=1)
    time.sleep(0.3)  # A's lease lapses mid-frame
    while b.poll():
        pass
    ((_, event),) = client.xrange(events_stream("cam"))
    committed = b.store.read(event[b"key"].decode())
    with pytest.raises(LeaseLost):
        a._reconstruct("cam", a.states["cam"], delivery)
    assert b.store.read(event[b"key"].decode()) == committed
    assert event[b"worker"] == b"B"


def test_an_owner_whose_lease_lapsed_reads_no_new_entries(
    client: redis.Redis, tmp_path: Path
) -> None:
    """A pauses past its lease between taking the device and reading it; B takes over.
    When A goes on to read, it gets nothing and lets the device go, so no entry is left
    pending at A behind frames B has done."""
    a, b = device_worker(client, tmp_path, "A", 100), device_worker(client, tmp_path, "B")
    publish_frame(client, frame("cam", 0), maxlen=10)
    client.sadd(DEVICES_SET, "cam")
    assert a._hold("cam")
    time.sleep(0.3)  # A's lease lapses
    b.poll()
    publish_frame(client, frame("cam", 1), maxlen=10)
    with pytest.raises(LeaseLost):
        a._drain("cam")
    assert client.xpending(frame_stream("cam"), "workers")["pending"] == 0
    while b.poll():
        pass
    events = [e[b"sequence"] for _, e in client.xrange(events_stream("cam"))]
    assert events == [b"0", b"1"]


def test_a_frames_queue_wait_ends_when_it_is_read_not_when_it_is_stored(
    client: redis.Redis, tmp_path: Path
) -> None:
    """A frame read at once and decoded in 0.5 s was recorded as having waited 0.5 s in
    the queue (its decode and store counted as waiting). The wait recorded ends by the
    time its decode starts (both in ms of the same clock), however long that takes."""
    inner = make_frame_decoder("independent", "itoh")
    decode_started_ms: list[int] = []

    def slow_decode(state: DeviceState, message: FrameMessage) -> DecodedFrame:
        decode_started_ms.append(time.time_ns() // 1_000_000)
        time.sleep(0.05)
        return inner(state, message)

    consumer = DeviceConsumer(
        client, ResultStore(tmp_path / RESULTS_DIR, retention_s=3600), owner="w1",
        lease_ms=5000, max_deliveries=3, decode=slow_decode, stop=threading.Event(),
    )  # fmt: skip
    publish_frame(client, frame("a", 0), maxlen=10)
    [(entry_id, _)] = client.xrange(frame_stream("a"))
    published_ms = int(entry_id.split(b"-")[0])
    consumer.poll()
    waited = {f.name: f for f in read_metrics(client)}["queue_wait_seconds"].samples[0]
    assert waited.count == 1
    assert waited.value * 1000 <= decode_started_ms[0] - published_ms + 1e-6


def test_after_a_restarted_cameras_first_frame_fails_its_next_frames_are_decoded(
    client: redis.Redis, consumer: DeviceConsumer
) -> None:
    """The camera restarts its counter (DISCONT at 0) and that first frame cannot be
    decoded (1 x 1 pixels): it is dead-lettered, and frames 1 and 2 that follow it are
    decoded. The device's newest done sequence used to stay at the old run's 5, so
    frames 1..5 of the new run were passed over as stale."""
    for sequence in range(6):
        publish_frame(client, frame("a", sequence), maxlen=100)
    restart = frame("a", 0)
    tiny = FrameMessage("a", 0, 0, restart.codes[:1, :1], restart.params, discont=True)
    publish_frame(client, tiny, maxlen=100)
    for sequence in (1, 2):
        publish_frame(client, frame("a", sequence), maxlen=100)
    while consumer.poll():
        pass
    (letter,) = dead_letters(client)
    assert b"no neighbours" in letter[b"message"]
    events = [fields for _, fields in client.xrange(events_stream("a"))]
    assert [(e[b"type"], e[b"sequence"]) for e in events][-3:] == [
        (b"failed", b"0"), (b"frame", b"1"), (b"frame", b"2")]
    assert consumer.states["a"].last_sequence == 2


def test_a_frame_committed_just_before_redis_refused_writes_is_counted(
    client: redis.Redis, consumer: DeviceConsumer
) -> None:
    """The frame was counted after its commit, in a separate write: Redis refusing
    writes (full, or restarting) right after the commit left a stored frame out of
    frames_processed_total for good ('frame metrics not recorded'). It is counted in
    the commit now."""
    commit = consumer._commit

    def commit_then_fill_redis(**kwargs: object) -> object:
        done = commit(**kwargs)
        client.config_set("maxmemory", 1)
        return done

    consumer._commit = commit_then_fill_redis  # type: ignore[assignment]
    publish_frame(client, frame("a", 0), maxlen=10)
    try:
        with contextlib.suppress(redis.exceptions.ResponseError):
            consumer.poll()
    finally:
        client.config_set("maxmemory", 0)
    assert client.xlen(frame_stream("a")) == 0
    processed = {f.name: f for f in read_metrics(client)}["frames_processed_total"]
    assert [(s.labels, s.value) for s in processed.samples] == [({"device": "a"}, 1)]


def test_a_frame_failing_on_an_internal_error_tells_the_client_what_to_do_not_the_hosts_paths(
    client: redis.Redis, consumer: DeviceConsumer, tmp_path: Path
) -> None:
    """A frame whose file cannot be stored (an OSError naming the results folder) is
    retried, then given up: its 'failed' event used to carry the exception's text, the
    host's paths included; it now says what happened and what to do, and the dead
    letter keeps the exception for the operator."""

    def read_only(key: str, data: bytes, *, replace: bool = True) -> Path:
        raise OSError(30, "Read-only file system", str(tmp_path / RESULTS_DIR))

    consumer.store.write = read_only  # type: ignore[method-assign]
    publish_frame(client, frame("a", 0), maxlen=10)
    consumer.poll()
    (event,) = [fields for _, fields in client.xrange(events_stream("a"))]
    assert event[b"type"] == b"failed" and event[b"code"] == b"internal_error"
    assert str(tmp_path).encode() not in event[b"message"]
    assert b"retry later" in event[b"message"]
    (letter,) = dead_letters(client)
    assert letter[b"code"] == b"internal_error"
    assert letter[b"message"].startswith(b"OSError: [Errno 30] Read-only file system")


def test_a_frame_too_bright_for_its_exr_at_the_cameras_gain_says_to_raise_it_by_control(
    client: redis.Redis, consumer: DeviceConsumer
) -> None:
    """A camera set to gain 1e-300 (``set_exposure``, accepted: a frame can carry it) sent
    frames whose scene values (x / gain) float32 cannot hold: each failed with "if that
    gain is not the frame's, give the right one", a remedy for an upload, though a
    device frame's gain is the camera's. The failure now says to send a set_exposure
    command with a higher gain to the device's control route."""
    sent = frame("a", 0)
    tiny_gain = sent.params.model_copy(update={"gain": 1e-300})
    publish_frame(client, FrameMessage("a", 0, 0, sent.codes, tiny_gain), maxlen=10)
    consumer.poll()
    (event,) = [fields for _, fields in client.xrange(events_stream("a"))]
    assert event[b"type"] == b"failed" and event[b"code"] == b"output_overflow"
    message = event[b"message"].decode()
    assert "give the right one" not in message
    assert "the camera's gain 1e-300" in message
    assert "set_exposure command with a higher gain to POST /v1/devices/a/control" in message


def test_a_frame_meeting_a_broken_model_install_fails_at_once_and_the_stream_goes_on(
    client: redis.Redis, tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
    caplog: pytest.LogCaptureFixture,
) -> None:
    """A stream decoded by mantissanet-small, its modulo model file not its card's: each
    modulo frame raised ModelFileError, an OSError, so it was retried to its last
    delivery (a traceback each time, the stream held up meanwhile), then failed as
    ``internal_error`` ("retry later, or report it"). Each now fails at its first
    delivery as ``model_unavailable``, without the host's paths; its dead letter names
    the file and what to do, the log says so in one line, and a mantissa frame after
    them is decoded."""
    break_model_file(monkeypatch, "mantissanet-small", "modulo")
    consumer = DeviceConsumer(
        client, ResultStore(tmp_path / RESULTS_DIR, retention_s=3600), owner="w1",
        lease_ms=5000, max_deliveries=3, stop=threading.Event(),
        decode=make_frame_decoder("independent", "mantissanet-small"),
    )  # fmt: skip
    hard = residue_frame()
    for sequence in (0, 1):
        publish_frame(client, FrameMessage("a", sequence, sequence * 1000, hard.codes,
                                           hard.params), maxlen=10)  # fmt: skip
    sensor = ramp_frame(size=16, params=SensorParams(encoding="mantissa", bits=8))
    publish_frame(client, FrameMessage("a", 2, 2000, sensor.codes, sensor.params), maxlen=10)
    while consumer.poll():
        pass
    events = [fields for _, fields in client.xrange(events_stream("a"))]
    assert [(e[b"type"], e.get(b"code")) for e in events] == [
        (b"failed", b"model_unavailable"), (b"failed", b"model_unavailable"), (b"frame", None)]
    assert b"cannot decode modulo frames" in events[0][b"message"]
    assert str(learned.ONNX_DIR).encode() not in events[0][b"message"]
    letters = dead_letters(client)
    assert [(letter[b"code"], letter[b"deliveries"]) for letter in letters] == [
        (b"model_unavailable", b"1"), (b"model_unavailable", b"1")]
    assert b"mantissanet-small-modulo.onnx" in letters[0][b"message"]
    assert b"restore it" in letters[0][b"message"]
    assert "Traceback" not in caplog.text and caplog.text.count("model install is broken") == 1
    assert client.xlen(frame_stream("a")) == 0 and consumer.states["a"].last_sequence == 2
