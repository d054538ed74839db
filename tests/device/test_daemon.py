"""The daemon against a virtual SCAMP-5 on a real pty and a real redis-server."""

from __future__ import annotations

import dataclasses
import json
import logging
import os
import re
import threading
import tty
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
import redis
import serial

from device import link_protocol as lp
from device.commands import FrameRateCommand
from device.daemon import DaemonConfig, DeviceDaemon
from device.datasets import DatasetLimits
from device.faults import Faults
from device.link_parser import LinkParser
from device.sim_link import PtyEndpoint, TcpEndpoint
from device.simulator import CameraSettings, VirtualScamp5
from models.formation import SensorParams
from tests.device.conftest import (
    health,
    newest_sequence,
    start_streaming,
    stream_frames,
    wait_for,
    wire,
)
from worker.device_registry import forget_device
from worker.embedded_redis import EmbeddedRedis
from worker.frame_message import FrameMessage
from worker.queue import publish_frame
from worker.redis_keys import (
    DEVICES_SET,
    control_cursor_key,
    control_stream,
    events_stream,
    health_key,
)


def finish_clean(link, frames: int) -> None:
    """Turn the faults off and send one more intact frame, so a trailing loss shows as a gap.
    The frame waits until the daemon is connected: sent while a disconnect fault still
    has the link down, it would be lost for good."""
    assert wait_for(lambda: link.camera.done(), 60)
    link.camera.faults = Faults()
    assert wait_for(lambda: link.daemon.health.state == "connected", 30)
    link.camera.max_frames = frames + 1
    assert wait_for(lambda: link.camera.done(), 30)
    assert wait_for(lambda: link.daemon.health.last_sequence == link.camera.sequence - 1, 30)
    last = link.camera.sequence - 1
    client = link.daemon.publisher.client
    assert wait_for(lambda: stream_frames(client, "cam1")[-1].sequence == last, 10)


def event_types(client: redis.Redis) -> set[str]:
    return {fields[b"type"].decode() for _, fields in client.xrange(events_stream("cam1"))}


def test_frames_arrive_in_order_with_correct_content(link, client: redis.Redis) -> None:
    with link(40) as run:
        assert wait_for(lambda: run.daemon.health.counts["frames_ok"] >= 40)
        frames = stream_frames(client, "cam1")
        assert [f.sequence for f in frames] == list(range(40))
        for frame in frames:
            truth = run.camera.ground_truth(frame.sequence)
            np.testing.assert_array_equal(frame.codes, truth.codes)
            assert frame.params.encoding == "modulo" and frame.params.gain == truth.params.gain
        assert [f.discont for f in frames] == [True] + [False] * 39
        assert client.sismember(DEVICES_SET, "cam1")
        assert wait_for(lambda: health(client, "cam1").get("frames_ok") == "40", 5)
    stats = health(client, "cam1")
    assert stats["sequence_gaps"] == "0" and stats["dropped_bad_crc"] == "0"
    assert json.loads(stats["settings"])["width"] == 256


def test_corrupted_bytes_drop_exactly_the_damaged_packets(link, client: redis.Redis) -> None:
    faults = Faults(corrupt_bytes=0.01, burst_len=1024, seed=3)
    with link(40, faults=faults) as run:
        finish_clean(run, 40)
        damaged = {seq for seq, sent in run.camera.sent.items() if not sent.intact}
        frames = stream_frames(client, "cam1")
        published = {f.sequence for f in frames}
        assert 5 <= len(damaged) <= 35, "the fault rate should damage some packets, not all"
        assert published == set(run.camera.sent) - damaged
        for frame in frames:
            np.testing.assert_array_equal(frame.codes,
                                          run.camera.ground_truth(frame.sequence).codes)
            assert frame.discont == (frame.sequence == 0 or frame.sequence - 1 in damaged)
        counts = run.daemon.health.counts
        assert counts["frames_missing"] == len(damaged)
        parser_drops = sum(counts[f"dropped_{c}"] for c in
                           ("bad_header", "bad_crc", "truncated", "oversize"))
        assert 0 < parser_drops <= len(damaged)
        assert wait_for(lambda: "drop" in event_types(client), 5)


def test_a_link_that_damages_packets_is_warned_of_in_the_log(
        link, client: redis.Redis, caplog: pytest.LogCaptureFixture) -> None:
    """Before, only the health hash counted damaged packets: a link losing a third of
    its frames to bad checksums and cut packets (simulate-device --corrupt-bytes 0.001
    --truncate 0.1) wrote not a line to the daemon's log. One warning (at most every
    30 s) names the causes and what to check."""
    faults = Faults(corrupt_bytes=0.01, burst_len=1024, truncate_packets=0.2, seed=3)
    with caplog.at_level(logging.WARNING, logger="device.daemon"), link(40, faults=faults) as run:
        finish_clean(run, 40)
    [warning] = [r.getMessage() for r in caplog.records if "dropped as damaged" in r.getMessage()]
    assert warning.startswith(f"device cam1's link {run.daemon.config.port}: packets dropped")
    assert re.search(r"damaged \((bad_header|bad_crc|truncated|oversize) [1-9]", warning)
    assert "garbage bytes" in warning
    assert "check the camera's cable" in warning


def test_disconnect_mid_stream_reconnects_and_marks_discont(link, client: redis.Redis) -> None:
    faults = Faults(disconnect_every=15, disconnect_s=0.3)
    with link(40, faults=faults) as run:
        finish_clean(run, 40)
        frames = stream_frames(client, "cam1")
        assert run.daemon.health.counts["reconnects"] >= 2
        assert wait_for(lambda: "reconnect" in event_types(client), 5)
        sequences = [f.sequence for f in frames]
        assert sequences == sorted(set(sequences))
        for cut in (14, 29):
            after = next(f for f in frames if f.sequence >= cut)
            assert after.discont
        for prev, frame in zip(frames, frames[1:], strict=False):
            if frame.sequence == prev.sequence + 1 and frame.sequence not in (14, 29):
                assert not frame.discont
            np.testing.assert_array_equal(frame.codes,
                                          run.camera.ground_truth(frame.sequence).codes)


def test_drops_stalls_and_bogus_lengths(link, client: redis.Redis) -> None:
    faults = Faults(drop_packets=0.1, oversize_packets=0.2, stall_every=7, stall_s=0.2, seed=5)
    with link(40, faults=faults) as run:
        finish_clean(run, 40)
        lost = {seq for seq, sent in run.camera.sent.items() if not sent.intact}
        assert lost, "some packets should have been dropped"
        assert {f.sequence for f in stream_frames(client, "cam1")} == set(run.camera.sent) - lost
        counts = run.daemon.health.counts
        assert counts["frames_missing"] == len(lost)
        assert counts["dropped_oversize"] > 0 and counts["dropped_truncated"] == 0


def test_a_stall_longer_than_the_partial_timeout_drops_only_that_packet(
        link, client: redis.Redis) -> None:
    faults = Faults(stall_every=5, stall_s=2.0)
    with link(15, faults=faults, partial_timeout_s=0.7) as run:
        finish_clean(run, 15)
        published = {f.sequence for f in stream_frames(client, "cam1")}
        assert published == set(range(16)) - {4, 9, 14}
        assert run.daemon.health.counts["dropped_truncated"] == 3


def test_tcp_link_reconnects(link, client: redis.Redis) -> None:
    faults = Faults(disconnect_every=12, disconnect_s=0.3)
    with link(30, faults=faults, endpoint=TcpEndpoint()) as run:
        assert run.daemon.config.port.startswith("socket://127.0.0.1:")
        finish_clean(run, 30)
        frames = stream_frames(client, "cam1")
        assert run.daemon.health.counts["reconnects"] >= 1
        assert next(f for f in frames if f.sequence >= 11).discont
        for frame in frames:
            np.testing.assert_array_equal(frame.codes,
                                          run.camera.ground_truth(frame.sequence).codes)


def test_redis_restart_daemon_resumes(link, client: redis.Redis,
                                      redis_server: EmbeddedRedis) -> None:
    with link(10_000) as run:
        assert wait_for(lambda: run.daemon.health.counts["frames_ok"] >= 10)
        redis_server.stop()
        assert wait_for(lambda: run.daemon.health.counts["dropped_redis_unavailable"] > 0, 20)
        redis_server.start()
        before = run.daemon.health.counts["frames_ok"]
        assert wait_for(lambda: run.daemon.health.counts["frames_ok"] >= before + 10, 30)
        frames = stream_frames(client, "cam1")
        sequences = [f.sequence for f in frames]
        assert sequences == sorted(sequences)
        gap = next(i for i in range(1, len(frames)) if sequences[i] != sequences[i - 1] + 1)
        assert frames[gap].discont
        assert wait_for(lambda: int(health(client, "cam1").get("frames_ok", 0)) > before, 5)


def test_control_stream_commands_reach_the_camera(link, client: redis.Redis) -> None:
    with link(10_000) as run:
        assert wait_for(lambda: run.daemon.health.counts["frames_ok"] >= 3)
        client.xadd(control_stream("cam1"), {"command": "set_encoding", "encoding": "mantissa",
                                             "alpha": "4", "bits": "10"})
        client.xadd(control_stream("cam1"), {"command": "set_exposure", "gain": "0.5",
                                             "integration_ns": "2000000"})
        client.xadd(control_stream("cam1"), {"command": "fly"})
        assert wait_for(lambda: run.camera.settings.encoding == "mantissa"
                        and run.camera.settings.exposure_gain == 1.0, 10)
        seen = run.camera.sequence
        assert wait_for(lambda: run.daemon.health.last_sequence > seen + 2, 10)
        client.xadd(control_stream("cam1"), {"command": "stop"})
        assert wait_for(lambda: not run.camera.settings.running, 10)
        # The daemon got frames past ``seen``; its publisher may still have them queued.
        assert wait_for(lambda: newest_sequence(client, "cam1")
                        == run.daemon.health.last_sequence, 30)
        frames = [f for f in stream_frames(client, "cam1") if f.sequence > seen]
        assert frames and all(f.params.encoding == "mantissa" and f.params.alpha == 4.0
                              and f.params.bits == 10 and f.codes.dtype == np.uint16
                              for f in frames)
        counts = run.daemon.health.counts  # counted after the write the camera obeys
        assert wait_for(lambda: counts["control_sent"] == 3 and counts["control_rejected"] == 1, 5)


def test_bracketed_capture_stores_a_reference_pair(link, client: redis.Redis,
                                                   tmp_path: Path) -> None:
    from models.frames import read_frame
    from models.hdr_io import read_hdr

    with link(10_000) as run:
        assert wait_for(lambda: run.daemon.health.counts["frames_ok"] >= 2)
        client.xadd(control_stream("cam1"), {"command": "bracket"})
        assert wait_for(lambda: run.daemon.health.counts["brackets_saved"] == 1, 20)
        wrapped_seq = next(s for s, sent in run.camera.sent.items() if sent.bracket_count)
        scene = run.camera.scene.render(run.camera.sent[wrapped_seq].index)
    (folder,) = (tmp_path / "data" / "datasets" / "cam1").glob(f"*-{wrapped_seq:010d}")
    reference = read_hdr(folder / "reference.exr").pixels
    relative = np.abs(reference - scene) / scene
    # Stated accuracy of the merge (8-bit codes, shot + read noise): median 1 %, 99th pct 5 %.
    assert np.median(relative) < 0.01 and np.quantile(relative, 0.99) < 0.05
    frame = read_frame(folder / "wrapped.png")
    np.testing.assert_array_equal(frame.codes, run.camera.ground_truth(wrapped_seq).codes)
    meta = json.loads((folder / "meta.json").read_text())
    assert meta["exposure_gains"] == [1 / 16, 1 / 8, 1 / 4, 1 / 2, 1.0]
    assert not any(f.sequence >= wrapped_seq and f.sequence < wrapped_seq + 6
                   for f in stream_frames(client, "cam1"))


def test_a_port_that_will_not_open_is_reported(
        client: redis.Redis, tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    missing = tmp_path / "no-such-tty"
    config = DaemonConfig(port=str(missing), device="cam1", backoff_max_s=0.05)
    with caplog.at_level(logging.WARNING, logger="device.daemon"):
        daemon = DeviceDaemon(config, client).start()
        try:
            assert wait_for(lambda: health(client, "cam1").get("port_error", ""), 10)
            assert wait_for(lambda: daemon.health.counts["reconnects"] == 0
                            and len(caplog.records) >= 1, 5)
            assert health(client, "cam1")["state"] == "connecting"
        finally:
            daemon.stop()
    fields = health(client, "cam1")
    assert fields["state"] == "stopped" and str(missing) in fields["port_error"]
    warnings = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert warnings and f"cannot open {missing}" in warnings[0]
    assert len(warnings) < 5  # one per outage, then every WARN_EVERY attempts


def test_a_wild_sequence_jump_is_a_gap_not_trillions_of_missing_frames(
        client: redis.Redis) -> None:
    daemon = DeviceDaemon(DaemonConfig(port="loop://", device="cam9"), client)
    codes = np.zeros((4, 4), np.uint8)
    for sequence in (0, 1, 5, 2**64 - 1):
        daemon._on_data(lp.DataPacket(sequence, 0, "modulo", 2.0, 8, 1.0, codes))
    assert daemon.health.counts["sequence_gaps"] == 2
    assert daemon.health.counts["frames_missing"] == 3


def test_frames_sent_while_the_link_was_down_are_a_gap_of_missing_frames(
        client: redis.Redis, tmp_path: Path) -> None:
    """The cable was pulled while the camera counted on: the reconnect forgot the last
    sequence and counted no gap, unlike a daemon restart. The first frame of each link is
    seen against the last of the one before (a counter that restarted or jumped wildly
    is a gap only) and still carries discont."""
    camera = PtyEndpoint(tmp_path / "scamp5")
    config = DaemonConfig(port=camera.url, device="cam1", backoff_max_s=0.05)
    daemon = DeviceDaemon(config, client).start()
    try:
        for reconnects, sequences in enumerate([(0, 1, 2), (3,), (10, 11), (0,), (2**40,)]):
            if reconnects:
                camera.disconnect()  # the cable is pulled and plugged back
                camera.reconnect()
            assert wait_for(lambda n=reconnects: daemon.health.counts["reconnects"] == n
                            and daemon.health.state == "connected", 10)
            camera.write(wire(*sequences))
            assert wait_for(lambda last=sequences[-1]: daemon.health.last_sequence == last, 10)
    finally:
        daemon.stop()
        camera.close()
    counts = health(client, "cam1")
    assert (counts["sequence_gaps"], counts["frames_missing"]) == ("3", "6")
    assert [(f.sequence, f.discont) for f in stream_frames(client, "cam1")] == [
        (0, True), (1, False), (2, False), (3, True), (10, True), (11, False), (0, True),
        (2**40, True)]


def bracket_packets(first: int, code: int = 100) -> list[lp.DataPacket]:
    """A 3-packet bracket from sequence ``first``: the wrapped frame, two clipped images,
    every pixel of each at ``code``."""
    codes = np.full((4, 4), code, np.uint8)
    return [lp.DataPacket(first + i, 0, "clip" if i else "modulo", 2.0, 8, 0.5 * 2**i, codes,
                          lp.FLAG_BRACKET, i, 3) for i in range(3)]


def test_a_restarted_sequence_keeps_earlier_pairs_within_the_dataset_bound(
        client: redis.Redis, tmp_path: Path) -> None:
    config = DaemonConfig(port="loop://", device="cam9", data_dir=tmp_path,
                          dataset_limits=DatasetLimits(max_pairs=3))
    daemon = DeviceDaemon(config, client)
    folders = tmp_path / "datasets" / "cam9"
    kept: list[list[str]] = []
    for first in (10, 10, 20, 30):  # the camera restarted its counter after the first bracket
        daemon._last_sequence = None
        for packet in bracket_packets(first):
            daemon._on_data(packet)
        kept.append([folder.name[-10:] for folder in sorted(folders.iterdir())])
    assert daemon.health.counts["brackets_saved"] == 4
    assert kept[2] == ["0000000010", "0000000010", "0000000020"]
    assert kept[3] == ["0000000010", "0000000020", "0000000030"]
    assert all((folder / "meta.json").is_file() for folder in folders.iterdir())


def test_a_bracket_saturated_at_every_pixel_is_counted_and_not_saved(
        client: redis.Redis, tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    """Its reference would hold only the darkest exposure's clip: no pair is stored, the
    bracket is counted in ``brackets_saturated`` and the log says why; the next bracket
    is saved."""
    daemon = DeviceDaemon(DaemonConfig(port="loop://", device="cam9", data_dir=tmp_path),
                          client)
    with caplog.at_level(logging.WARNING, logger="device.daemon"):
        for packet in bracket_packets(10, code=255):
            daemon._on_data(packet)
    assert daemon.health.counts["brackets_saturated"] == 1
    assert daemon.health.counts["brackets_saved"] == 0
    assert not (tmp_path / "datasets").exists()
    assert "bracket at sequence 10 not saved: every pixel is saturated" in caplog.text
    for packet in bracket_packets(13):
        daemon._on_data(packet)
    assert daemon.health.counts["brackets_saved"] == 1
    assert daemon.health.counts["brackets_saturated"] == 1


def test_a_bracket_whose_exposures_do_not_fit_is_abandoned_and_streaming_goes_on(
        client: redis.Redis, tmp_path: Path) -> None:
    """Each packet of the bracket is intact, but its last exposure is of another size:
    the bracket is counted incomplete, nothing is stored, and the next frame is
    published."""
    config = DaemonConfig(port="loop://", device="cam9", data_dir=tmp_path)
    daemon = DeviceDaemon(config, client)
    *fitting, last = bracket_packets(10)
    misfit = lp.DataPacket(last.sequence, 0, "clip", 2.0, 8, last.gain,
                           np.zeros((8, 8), np.uint8), lp.FLAG_BRACKET, 2, 3)
    after = lp.DataPacket(13, 0, "modulo", 2.0, 8, 1.0, np.zeros((4, 4), np.uint8))
    daemon._feed(b"".join(lp.encode_packet(p) for p in [*fitting, misfit, after]))
    assert daemon.health.counts["brackets_incomplete"] == 1
    assert not (tmp_path / "datasets").exists()
    daemon.publisher.start()
    daemon.publisher.stop()
    assert [frame.sequence for frame in stream_frames(client, "cam9")] == [13]


def test_a_packet_the_daemon_fails_on_is_counted_and_the_reader_goes_on(
        client: redis.Redis, caplog: pytest.LogCaptureFixture) -> None:
    """Whatever goes wrong handling one packet (here a publisher that raises stands in
    for a bug), the reader logs it with its traceback, counts the frame rejected and
    handles the next one."""
    daemon = DeviceDaemon(DaemonConfig(port="loop://", device="cam9"), client)
    handled: list[int] = []
    real = daemon.publisher.offer

    def offer(message) -> None:
        if message.sequence == 1:
            raise RuntimeError("not a client mistake")
        handled.append(message.sequence)
        real(message)

    daemon.publisher.offer = offer  # type: ignore[method-assign]
    packets = [lp.DataPacket(s, 0, "modulo", 2.0, 8, 1.0, np.zeros((4, 4), np.uint8))
               for s in range(3)]
    with caplog.at_level(logging.ERROR):
        daemon._feed(b"".join(lp.encode_packet(p) for p in packets))
    assert handled == [0, 2] and daemon.health.counts["dropped_rejected"] == 1
    assert "frame 1 could not be handled" in caplog.text


class StuckThenFreePort:
    """A port whose first write times out (the camera stopped reading), then accepts."""

    def __init__(self) -> None:
        self.written: list[bytes] = []
        self.stuck = True

    def write(self, data: bytes) -> int:
        if self.stuck:
            self.stuck = False
            raise serial.SerialTimeoutException("Write timeout")
        self.written.append(data)
        return len(data)


def test_a_command_whose_write_timed_out_goes_first_on_the_next_link(
        client: redis.Redis) -> None:
    """The timeout ends the link (the daemon reconnects); the command is not lost but
    written first once the port is back, before commands queued after it."""
    daemon = DeviceDaemon(DaemonConfig(port="loop://", device="cam9"), client)
    daemon.send_command("1-0", FrameRateCommand(command="set_frame_rate", fps=5.0))
    daemon.send_command("2-0", FrameRateCommand(command="set_frame_rate", fps=7.0))
    port = StuckThenFreePort()
    with pytest.raises(serial.SerialTimeoutException):
        daemon._flush_outbox(port)
    daemon._flush_outbox(port)
    parser = LinkParser(lp.DEFAULT_MAX_PAYLOAD)
    sent = [packet for data in port.written for packet in parser.feed(data)]
    assert [getattr(packet, "fps", None) for packet in sent] == [5.0, 7.0]
    assert daemon.health.counts["control_sent"] == 2


def test_a_command_a_stopped_daemon_never_sent_reaches_the_next_one(
        client: redis.Redis, tmp_path: Path) -> None:
    """The camera is unplugged: the daemon takes the command but cannot send it, then
    stops. The device's cursor had moved past it when it was taken, so the next daemon
    never sent it, although the API had answered 202."""
    port = tmp_path / "scamp5"
    config = DaemonConfig(port=str(port), device="cam1", data_dir=tmp_path / "data",
                          backoff_max_s=0.2)
    first = DeviceDaemon(config, client)
    first.start()
    assert wait_for(lambda: client.exists(control_cursor_key("cam1")), 10)  # its place
    client.xadd(control_stream("cam1"), {"command": "set_frame_rate", "fps": "7"})
    assert wait_for(lambda: first._outbox.qsize() == 1, 10)  # taken, not sent
    first.stop()
    camera = VirtualScamp5(PtyEndpoint(port), settings=CameraSettings(fps=50), seed=7)
    second = DeviceDaemon(config, client)
    try:
        start_streaming(second, camera)
        assert wait_for(lambda: camera.settings.fps == 7.0, 10)
        assert wait_for(lambda: second.health.counts["control_sent"] == 1, 5)
    finally:
        camera.stop()
        second.stop()


def test_a_cleanly_stopped_daemon_says_so_and_its_device_can_be_forgotten_at_once(
        client: redis.Redis, tmp_path: Path) -> None:
    """It left 'disconnected', and forgetting the device was refused for 10 s with
    'stop it and retry' although it had stopped."""
    daemon = DeviceDaemon(DaemonConfig(port=str(tmp_path / "none"), device="cam1",
                                       data_dir=tmp_path / "data", backoff_max_s=0.2), client)
    daemon.start()
    assert wait_for(lambda: health(client, "cam1").get("state") == "connecting", 10)
    daemon.stop()
    assert health(client, "cam1")["state"] == "stopped"
    assert forget_device(client, "cam1", silent_after_s=10.0) == 0
    assert not client.sismember(DEVICES_SET, "cam1")


def events_since(client: redis.Redis, device: str, count: int) -> list[dict[str, str]]:
    """The events of ``device`` after its first ``count``."""
    entries = client.xrange(events_stream(device))[count:]
    return [{k.decode(): v.decode() for k, v in fields.items() if k != b"written_ns"}
            for _, fields in entries]


@pytest.mark.parametrize("frames_first", [True, False],
                         ids=["frames-before-take-over", "take-over-before-frames"])
def test_a_restarted_daemon_goes_on_from_its_predecessors_counters(
        client: redis.Redis, frames_first: bool) -> None:
    """A restart reset frames, drops, gaps and reconnects to 0, and an operator watching
    them lost their history. The gauges start afresh; the counts carried over are not
    reported again as events, whether the new daemon's first frames come before it
    reaches Redis or after."""
    config = DaemonConfig(port="loop://", device="cam9")
    first = DeviceDaemon(config, client)
    first.claim.take()
    first.health.add("reconnects", 2)
    first.health.port_error = "unplugged"
    first._feed(wire(0, 1, 2, damaged=3) + wire(4))
    first.publisher.start()
    first.publisher.stop()
    first.claim.release()  # a clean stop, as run() ends
    before = health(client, "cam9")
    assert (before["frames_ok"], before["dropped_bad_crc"], before["frames_missing"]) == (
        "4", "1", "1")
    events = client.xlen(events_stream("cam9"))

    second = DeviceDaemon(config, client)
    second.claim.take()
    if not frames_first:
        second.publisher._housekeeping()
    second._feed(wire(5, damaged=6))
    second.publisher.start()
    second.publisher.stop()
    after = health(client, "cam9")
    assert {name: after[name] for name in (
        "frames_received", "frames_ok", "dropped_bad_crc", "sequence_gaps", "frames_missing",
        "reconnects", "state", "port_error")} == {
        "frames_received": "5", "frames_ok": "5", "dropped_bad_crc": "2",
        "sequence_gaps": "1", "frames_missing": "1", "reconnects": "2",
        "state": "connecting", "port_error": ""}
    assert int(after["garbage_bytes"]) > int(before["garbage_bytes"])
    assert events_since(client, "cam9", events) == [
        {"type": "drop", "dropped": "2", "new": "1", "causes": "bad_crc:1"}]


def test_frames_a_killed_daemon_published_after_its_last_health_write_are_not_missing(
        client: redis.Redis) -> None:
    """A daemon killed (SIGKILL) 0.25 s after its last health write had published frames
    its hash does not show: the stream has them, so they are not counted missing."""
    config = DaemonConfig(port="loop://", device="cam9")
    first = DeviceDaemon(config, client)
    first.claim.take()
    first._feed(wire(0, 1))
    first.publisher.start()
    first.publisher.stop()  # its last health write: last_sequence 1
    for sequence in (2, 3):  # published, then killed before the next health write
        publish_frame(client, FrameMessage("cam9", sequence, 0, np.zeros((4, 4), np.uint8),
                                           SensorParams(), False), maxlen=100)
    first.claim.release()  # as a killed daemon's claim lapses
    restart(client, wire(4, 6), take_over_first=False)
    counts = health(client, "cam9")
    assert (counts["sequence_gaps"], counts["frames_missing"], counts["last_sequence"]) == (
        "1", "1", "6")


def test_a_daemon_whose_device_another_daemon_holds_takes_none_of_its_counters(
        client: redis.Redis) -> None:
    """The hash is the other daemon's: its counts are not this camera's history."""
    config = DaemonConfig(port="loop://", device="cam9")
    first = DeviceDaemon(config, client)
    first.claim.take()
    first._feed(wire(0, 1, 2))
    first.publisher._housekeeping()
    second = DeviceDaemon(config, client)
    second._feed(wire(0))
    second.publisher._housekeeping()
    assert second.health.counts["frames_received"] == 1


def restart(client: redis.Redis, data: bytes, *, take_over_first: bool) -> DeviceDaemon:
    """A daemon of cam9 that reads ``data`` from its camera, publishes it and stops
    cleanly; with ``take_over_first`` it reaches Redis before its first frame."""
    daemon = DeviceDaemon(DaemonConfig(port="loop://", device="cam9"), client)
    daemon.claim.take()
    if take_over_first:
        daemon.publisher._housekeeping()
    daemon._feed(data)
    daemon.publisher.start()
    daemon.publisher.stop()
    daemon.claim.release()
    return daemon


@pytest.mark.parametrize("take_over_first", [False, True],
                         ids=["frames-before-take-over", "take-over-before-frames"])
def test_frames_sent_while_no_daemon_ran_are_a_gap_of_missing_frames(
        client: redis.Redis, take_over_first: bool) -> None:
    """The camera counted on while no daemon read it: the first frame after the restart
    is seen against the last one before it (also across a daemon that got no frame),
    the worker still gets a discont, and a wild jump is a counter reset, not frames."""
    restart(client, wire(0, 1, 2), take_over_first=take_over_first)
    restart(client, b"", take_over_first=take_over_first)  # the camera was unplugged
    assert health(client, "cam9")["last_sequence"] == "2"
    restart(client, wire(10, 11), take_over_first=take_over_first)
    counts = health(client, "cam9")
    assert (counts["sequence_gaps"], counts["frames_missing"]) == ("1", "7")
    assert [(f.sequence, f.discont) for f in stream_frames(client, "cam9")] == [
        (0, True), (1, False), (2, False), (10, True), (11, False)]
    restart(client, wire(12), take_over_first=take_over_first)  # no frame lost: no gap
    assert stream_frames(client, "cam9")[-1].discont  # as every new daemon's first frame
    restart(client, wire(2**40), take_over_first=take_over_first)
    counts = health(client, "cam9")
    assert (counts["sequence_gaps"], counts["frames_missing"]) == ("2", "7")


def test_packets_dropped_as_malformed_are_logged_with_why(
        client: redis.Redis, caplog: pytest.LogCaptureFixture) -> None:
    """A camera on a real pty sends a frame whose header says 17 bits: it is dropped as
    malformed, and the log says which field is wrong and what range it must be in (a
    counter alone left a camera set wrong losing every frame without a word)."""
    master, slave = os.openpty()
    tty.setraw(master)
    tty.setraw(slave)
    codes = np.zeros((4, 4), np.uint16)
    payload = lp.encode_data(lp.DataPacket(0, 0, "modulo", 2.0, 16, 1.0, codes))[8:-4]
    bits_17 = lp.frame_packet(lp.PacketType.DATA, payload[:22] + bytes([17]) + payload[23:])
    intact = lp.encode_data(lp.DataPacket(1, 0, "modulo", 2.0, 16, 1.0, codes))
    daemon = DeviceDaemon(DaemonConfig(port=os.ttyname(slave), device="cam1"), client)
    try:
        with caplog.at_level(logging.WARNING, logger="device.daemon"):
            daemon.start()
            assert wait_for(lambda: daemon.health.state == "connected", 30)
            os.write(master, bits_17 + intact)
            assert wait_for(lambda: daemon.health.counts["frames_received"] == 1, 30)
    finally:
        daemon.stop()
        os.close(master)
        os.close(slave)
    assert daemon.health.counts["dropped_malformed"] == 1
    assert "dropped as malformed" in caplog.text and "bits 17 (must be 1..16)" in caplog.text


#: One lap of a 32-bit firmware sequence counter.
LAP = 2**32


def test_a_32_bit_sequence_counter_that_wraps_reads_as_consecutive(
        client: redis.Redis, tmp_path: Path) -> None:
    """The camera's firmware counts in 32 bits: its step from 2^32 - 1 to 0 was read as a
    counter reset (a gap, and a DISCONT keyframe for the decoders), and frames lost across
    the wrap were not counted missing. The host numbers the frames on from 2^32; a frame
    lost after the wrap is a gap of one, and a true reset is still a reset."""
    camera = PtyEndpoint(tmp_path / "scamp5")
    daemon = DeviceDaemon(DaemonConfig(port=camera.url, device="cam1"), client).start()
    try:
        assert wait_for(lambda: daemon.health.state == "connected", 30)
        for received, sequences in [(4, (LAP - 2, LAP - 1, 0, 1)), (5, (3,)), (6, (0,))]:
            camera.write(wire(*sequences))
            assert wait_for(lambda n=received: daemon.health.counts["frames_received"] == n, 30)
    finally:
        daemon.stop()
        camera.close()
    counts = health(client, "cam1")
    assert (counts["sequence_gaps"], counts["frames_missing"]) == ("2", "1")
    assert [(f.sequence, f.discont) for f in stream_frames(client, "cam1")] == [
        (LAP - 2, True), (LAP - 1, False), (LAP, False), (LAP + 1, False), (LAP + 3, True),
        (0, True)]


@pytest.mark.parametrize("take_over_first", [False, True],
                         ids=["frames-before-take-over", "take-over-before-frames"])
def test_a_restarted_daemon_goes_on_past_a_wrapped_counter(
        client: redis.Redis, take_over_first: bool) -> None:
    """The counter wrapped under the previous daemon: the next one's first frame follows
    the previous daemon's last (no gap), whether it reaches Redis before that frame or not."""
    restart(client, wire(LAP - 1, 0), take_over_first=take_over_first)
    restart(client, wire(1, 2), take_over_first=take_over_first)
    counts = health(client, "cam9")
    assert (counts["sequence_gaps"], counts["frames_missing"]) == ("0", "0")


def test_a_bracket_across_the_wrap_is_saved_beside_the_one_before_it(
        client: redis.Redis, tmp_path: Path) -> None:
    """A bracket whose packets straddle the wrap (2^32 - 1, 0, 1) was abandoned as out of
    order. It is saved, after the pair of the bracket before the wrap (pairs are named by
    the host's clock first, then the host's sequence number)."""
    daemon = DeviceDaemon(DaemonConfig(port="loop://", device="cam9", data_dir=tmp_path), client)
    for packet in [*bracket_packets(LAP - 4), *bracket_packets(LAP - 1)]:
        daemon._on_data(dataclasses.replace(packet, sequence=packet.sequence % LAP))
    assert (daemon.health.counts["brackets_saved"], daemon.health.counts["brackets_incomplete"],
            daemon.health.counts["sequence_gaps"]) == (2, 0, 0)
    names = sorted(folder.name for folder in (tmp_path / "datasets" / "cam9").iterdir())
    assert [int(name.partition("-")[2]) for name in names] == [LAP - 4, LAP - 1]


def test_a_bracket_leaves_the_reported_settings_those_of_the_streamed_frames(
        client: redis.Redis, tmp_path: Path) -> None:
    """The health's ``settings`` describe the frames the device streams: a bracket's
    exposures (clip images at other gains, never streamed) do not take their place.
    Before, the last exposure's showed until the next frame (10 s at 0.1 fps): ``GET
    /v1/devices/{id}`` said ``clip``, and a recording start with a decoder for the
    camera's encoding only was refused 422 "sends clip frames"."""
    daemon = DeviceDaemon(DaemonConfig(port="loop://", device="cam9", data_dir=tmp_path),
                          client)
    daemon._on_data(lp.DataPacket(9, 0, "modulo", 2.0, 8, 1.0, np.full((4, 4), 100, np.uint8)))
    streamed = daemon.health.settings
    assert streamed["encoding"] == "modulo" and streamed["gain"] == 1.0
    for packet in bracket_packets(10):
        daemon._on_data(packet)
    assert daemon.health.counts["brackets_saved"] == 1
    assert daemon.health.settings == streamed and daemon.health.last_sequence == 12


def not_a_client_mistake(*_args: object, **_kwargs: object) -> None:
    """A bug of the daemon's, where it does not expect one."""
    raise RuntimeError("not a client mistake")


def loop_port_with(data: bytes) -> Callable[[], serial.Serial]:
    """An opener of a loop:// port with ``data`` to read."""
    def opener() -> serial.Serial:
        port = serial.serial_for_url("loop://", timeout=0.05)
        port.write(data)
        return port
    return opener



def assert_health_says_crashed(client: redis.Redis, device: str) -> None:
    """The device's health says its daemon crashed on :func:`not_a_client_mistake`'s
    error, at 0 fps."""
    last = health(client, device)
    assert (last["state"], last.get("crash"), last["fps"]) == (
        "crashed", "RuntimeError: not a client mistake", "0.000"), last


def assert_stops_on_the_bug(daemon: DeviceDaemon, caplog: pytest.LogCaptureFixture,
                            monkeypatch: pytest.MonkeyPatch, logged: str) -> None:
    """Run ``daemon`` until it stops by itself, on :func:`not_a_client_mistake`'s
    RuntimeError: kept in ``crash``, logged once (``logged``) with its traceback, and
    not left to threading's excepthook."""
    uncaught: list[threading.ExceptHookArgs] = []
    monkeypatch.setattr(threading, "excepthook", uncaught.append)
    with caplog.at_level(logging.ERROR):
        daemon.start()
        assert daemon.wait(30)
        daemon.stop()
    assert isinstance(daemon.crash, RuntimeError) and daemon.failure is None
    errors = [r for r in caplog.records if r.levelno >= logging.ERROR]
    assert [r.getMessage() for r in errors] == [logged]
    assert errors[0].exc_info is not None
    assert uncaught == []


@pytest.mark.parametrize("where", ["opener", "parser"])
def test_an_unexpected_error_stops_the_daemon_logged_once_and_kept(
        client: redis.Redis, caplog: pytest.LogCaptureFixture,
        monkeypatch: pytest.MonkeyPatch, where: str) -> None:
    """A bug in the link's loops (here a port opener or a parser that raises) went to
    threading's excepthook, and the daemon looked stopped as by a stop (no failure): its
    command exited 0. It is now logged once with its traceback and kept in ``crash``;
    the health says it crashed, and on what."""
    opener = not_a_client_mistake if where == "opener" else loop_port_with(b"\0")
    daemon = DeviceDaemon(DaemonConfig(port="loop://", device="cam9"), client, opener=opener)
    monkeypatch.setattr(daemon._parser, "feed", not_a_client_mistake)
    assert_stops_on_the_bug(
        daemon, caplog, monkeypatch,
        "device cam9: the daemon stopped on an unexpected error; loop:// is no longer read")
    assert_health_says_crashed(client, "cam9")


def test_an_unexpected_error_in_publishing_stops_the_daemon_logged_once_and_kept(
        client: redis.Redis, caplog: pytest.LogCaptureFixture,
        monkeypatch: pytest.MonkeyPatch) -> None:
    """A bug in the publisher's thread (here a frame's publishing that raises) went to
    threading's excepthook, and the daemon read on: its frames dropped as queue_full, its
    health no longer written, its command running for good. It now stops the daemon as
    an unexpected error in the daemon's own thread does, logged once."""
    monkeypatch.setattr("device.publisher.publish_frame", not_a_client_mistake)
    daemon = DeviceDaemon(DaemonConfig(port="loop://", device="cam9"), client,
                          opener=loop_port_with(wire(0)))
    assert_stops_on_the_bug(
        daemon, caplog, monkeypatch,
        "device cam9: publishing stopped on an unexpected error; its frames are no longer "
        "published")
    assert_health_says_crashed(client, "cam9")


def test_a_crashed_device_forgotten_after_its_last_health_write_stays_forgotten(
        client: redis.Redis, monkeypatch: pytest.MonkeyPatch) -> None:
    """The publisher's last write says ``crashed``, and a crashed device may be forgotten
    at once: the daemon's own crash report, written after it, registered the device
    again, its health saying crashed."""
    port = serial.serial_for_url("loop://", timeout=0.05)
    daemon = DeviceDaemon(DaemonConfig(port="loop://", device="cam9"), client,
                          opener=lambda: port)
    stop_publishing = daemon.publisher.stop

    def stop_then_forget(*args: object) -> None:
        stop_publishing(*args)  # type: ignore[arg-type]
        assert health(client, "cam9")["state"] == "crashed"
        forget_device(client, "cam9", silent_after_s=10)

    monkeypatch.setattr(daemon.publisher, "stop", stop_then_forget)
    daemon.start()
    try:
        assert wait_for(lambda: health(client, "cam9").get("state") == "connected")
        monkeypatch.setattr(daemon._parser, "feed", not_a_client_mistake)
        port.write(b"\0")
        assert daemon.wait(30)
    finally:
        daemon.stop()
    assert isinstance(daemon.crash, RuntimeError)
    assert not client.exists(health_key("cam9"))
    assert not client.sismember(DEVICES_SET, "cam9")


def test_a_crash_of_publishing_leaves_the_health_saying_so(
        client: redis.Redis, monkeypatch: pytest.MonkeyPatch) -> None:
    """The publishing thread writes the health: once it had crashed, the device read
    ``connected`` for good (its last write) though the daemon had stopped. The daemon's
    own thread now writes that it crashed, and on what."""
    port = serial.serial_for_url("loop://", timeout=0.05)
    daemon = DeviceDaemon(DaemonConfig(port="loop://", device="cam9"), client,
                          opener=lambda: port)
    daemon.start()
    try:
        assert wait_for(lambda: health(client, "cam9").get("state") == "connected")
        monkeypatch.setattr("device.publisher.publish_frame", not_a_client_mistake)
        port.write(wire(0))
        assert daemon.wait(30)
    finally:
        daemon.stop()
    assert isinstance(daemon.crash, RuntimeError)
    assert_health_says_crashed(client, "cam9")


def test_the_frame_after_a_bracket_says_how_many_sequence_numbers_the_bracket_took(
        client: redis.Redis, tmp_path: Path) -> None:
    """A bracket's packets take sequence numbers but are never streamed: the next frame
    says how many (``bracketed``), so a recording tells them from frames lost on the link.
    Before, a recording across a bracket counted its packets in ``frames_skipped``, warned
    of frames "lost on the camera link" (check the cable) and measured the camera 14 %
    fast."""
    daemon = DeviceDaemon(DaemonConfig(port="loop://", device="cam9", data_dir=tmp_path),
                          client)
    frame = np.full((4, 4), 100, np.uint8)
    daemon._on_data(lp.DataPacket(9, 0, "modulo", 2.0, 8, 1.0, frame))
    for packet in bracket_packets(10):
        daemon._on_data(packet)
    daemon._on_data(lp.DataPacket(13, 0, "modulo", 2.0, 8, 1.0, frame))
    daemon._on_data(lp.DataPacket(14, 0, "modulo", 2.0, 8, 1.0, frame))
    daemon.publisher.start()
    daemon.publisher.stop()
    assert [(f.sequence, f.bracketed) for f in stream_frames(client, "cam9")] == [
        (9, 0), (13, 3), (14, 0)]
