"""The virtual SCAMP-5: scenes, encoding through the formation model, control packets over a
real TCP socket, brackets, faults and its link endpoints."""

from __future__ import annotations

import os
import socket
import threading
import time
from dataclasses import replace

import numpy as np
import pytest
import serial

from device import link_protocol as lp
from device.commands import FPS_RANGE
from device.faults import Faults
from device.link_parser import LinkParser
from device.scenes import ExrScene, ProceduralScene
from device.sim_link import LoopEndpoint, TcpEndpoint, open_endpoint
from device.simulator import MAX_SEED, SEQUENCE_ROOM, CameraSettings, VirtualScamp5
from models.errors import InvalidInputError
from models.formation import simulate
from tests.device.conftest import wait_for

HDRI = "models/data/hdri/lab.exr"


def test_procedural_scene_is_deterministic_smooth_and_moving() -> None:
    scene = ProceduralScene()
    a, b = scene.render(3), scene.render(4)
    assert a.shape == (256, 256) and a.min() > 0
    np.testing.assert_array_equal(a, scene.render(3))
    assert not np.array_equal(a, b)
    assert np.abs(np.diff(a, axis=1)).max() < 0.5  # Itoh-unwrappable at gain 1
    assert scene.brightness(0) == 0.5 and scene.brightness(120) == 1.5


def test_exr_scene_pans_across_the_image() -> None:
    scene = ExrScene([HDRI])
    assert scene.render(0).shape == (256, 256)
    np.testing.assert_array_equal(scene.render(1)[:, :-1], scene.render(0)[:, 1:])
    with pytest.raises(InvalidInputError, match="at least one"):
        ExrScene([])


def test_frames_are_the_formation_model_seeded_by_sequence() -> None:
    camera = VirtualScamp5(LoopEndpoint(), seed=5, history=10)
    params = camera.params_for(3)
    frame = camera.render(0, params)
    expected = simulate(camera.scene.render(0), params)
    np.testing.assert_array_equal(frame.codes, expected.codes)
    assert params.encoding == "modulo" and params.seed == 5 * 1_000_003 + 3
    with pytest.raises(InvalidInputError, match="history"):
        camera.ground_truth(99)


def test_a_seed_whose_frame_seeds_overflow_int64_is_refused_up_front() -> None:
    camera = VirtualScamp5(LoopEndpoint(), ProceduralScene(size=8), seed=MAX_SEED)
    assert camera.params_for(SEQUENCE_ROOM).seed == MAX_SEED * 1_000_003 + SEQUENCE_ROOM
    for seed in (MAX_SEED + 1, 9_300_000_000_000, -1):
        with pytest.raises(InvalidInputError, match=f"seed must be from 0 to {MAX_SEED}"):
            VirtualScamp5(LoopEndpoint(), seed=seed)


def read_packets(port: serial.SerialBase, parser: LinkParser, count: int) -> list[lp.DataPacket]:
    out: list[lp.DataPacket] = []
    deadline = time.monotonic() + 20
    while len(out) < count and time.monotonic() < deadline:
        out += [p for p in parser.feed(port.read(65536)) if isinstance(p, lp.DataPacket)]
    return out


def test_control_packets_over_tcp_change_the_camera() -> None:
    camera = VirtualScamp5(TcpEndpoint(), settings=CameraSettings(fps=100, running=False),
                           history=50).start()
    try:
        port = serial.serial_for_url(camera.endpoint.url, timeout=0.05)
        parser = LinkParser()
        for packet in (lp.EncodingPacket("mantissa", 12, 3.0), lp.ExposurePacket(2.0, 500_000),
                       lp.FrameRatePacket(80.0), lp.StartPacket()):
            port.write(lp.encode_control(packet))
        frames = read_packets(port, parser, 2)
        assert frames[0].encoding == "mantissa" and frames[0].bits == 12
        assert frames[0].alpha == 3.0 and frames[0].gain == 1.0
        assert frames[0].codes.dtype == np.uint16
        assert camera.settings.fps == 80.0
        port.write(lp.encode_control(lp.BracketPacket(3, 0.25, 2.0)))
        bracket = [p for p in read_packets(port, parser, 30) if p.flags & lp.FLAG_BRACKET][:4]
        assert [p.bracket_index for p in bracket] == [0, 1, 2, 3]
        assert [p.encoding for p in bracket] == ["mantissa", "clip", "clip", "clip"]
        assert [p.gain for p in bracket[1:]] == [0.25, 0.5, 1.0]
        assert all(p.bracket_count == 4 for p in bracket)
        port.write(lp.encode_control(lp.FrameRatePacket(-5.0)))  # invalid: ignored
        port.write(lp.encode_control(lp.StopPacket()))
        assert wait_for(lambda: not camera.settings.running, 5)
        assert camera.settings.fps == 80.0
        port.close()
    finally:
        camera.stop()


def test_a_camera_at_the_slowest_frame_rate_still_obeys_control_input() -> None:
    camera = VirtualScamp5(TcpEndpoint(), ProceduralScene(size=8),
                           CameraSettings(fps=FPS_RANGE[0])).start()
    try:
        port = serial.serial_for_url(camera.endpoint.url, timeout=0.05)
        assert wait_for(lambda: camera.frames_captured == 1, 5)
        port.write(lp.encode_control(lp.FrameRatePacket(50.0)))
        assert wait_for(lambda: camera.frames_captured >= 5, 3)  # not 10 s after the first
        assert camera.settings.fps == 50.0
        port.close()
    finally:
        camera.stop()


def test_fault_switches_damage_packets_as_described() -> None:
    wire = lp.encode_packet(lp.FrameRatePacket(1.0)) * 10
    assert Faults(drop_packets=1.0).apply(wire) == (b"", False)
    cut, intact = Faults(truncate_packets=1.0).apply(wire)
    assert cut == wire[: len(wire) // 2] and not intact
    data, intact = Faults(oversize_packets=1.0).apply(wire)
    assert intact and data.endswith(wire) and lp.unpack_header(data[:8])[1:] == (2**24 - 1, True)
    data, intact = Faults(corrupt_bytes=0.5, burst_len=4, seed=1).apply(wire)
    assert not intact and len(data) == len(wire)
    assert Faults().apply(wire) == (wire, True)
    faults = Faults(stall_every=3, disconnect_every=4)
    assert [faults.stall_now(i) for i in range(6)] == [False, False, True, False, False, True]
    assert [faults.disconnect_now(i) for i in range(5)] == [False, False, False, True, False]
    with pytest.raises(ValueError, match="corrupt_bytes"):
        Faults(corrupt_bytes=2.0)


def test_loop_endpoint_streams_to_a_reader() -> None:
    endpoint = LoopEndpoint()
    camera = VirtualScamp5(endpoint, settings=CameraSettings(fps=200), max_frames=3, history=5)
    parser = LinkParser()
    thread = threading.Thread(target=lambda: [camera.step() for _ in range(3)])
    thread.start()
    frames = read_packets(endpoint.port, parser, 3)
    thread.join()
    assert [f.sequence for f in frames] == [0, 1, 2]
    np.testing.assert_array_equal(frames[2].codes, camera.ground_truth(2).codes)


def test_tcp_disconnect_and_reconnect_keep_the_port() -> None:
    endpoint = TcpEndpoint()
    port = endpoint.port
    endpoint.disconnect()
    with pytest.raises(OSError):
        socket.create_connection(("127.0.0.1", port), timeout=1).close()
    assert endpoint.write(b"x") is False  # nobody connected: not delivered
    endpoint.reconnect()
    host = socket.create_connection(("127.0.0.1", port), timeout=1)
    assert wait_for(lambda: endpoint.write(b"hello"), 5)
    assert host.recv(16).endswith(b"hello")
    host.sendall(b"cmd")
    assert wait_for(lambda: endpoint.read() == b"cmd", 5)
    host.close()
    endpoint.close()


def test_open_endpoint_rejects_unknown_ports() -> None:
    with pytest.raises(InvalidInputError, match="unsupported simulator port"):
        open_endpoint("/dev/ttyUSB0")
    with pytest.raises(InvalidInputError, match="socket://HOST:PORT"):
        open_endpoint("socket://localhost")


def test_an_exposure_no_frame_can_hold_is_survived_and_undone(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """A gain and integration the API accepts one by one can together wrap pixels past
    int64 counts: the camera sends nothing (and says why, once) until they change."""
    endpoint = LoopEndpoint()
    camera = VirtualScamp5(endpoint, settings=CameraSettings(encoding="modulo"))
    draining = threading.Event()

    def drain() -> None:  # the loop holds 4096 bytes: the host must read
        while not draining.is_set():
            endpoint.port.read(65536)

    reader = threading.Thread(target=drain, daemon=True)
    reader.start()
    try:
        camera.settings = replace(camera.settings, gain=1e9, integration_ns=(1 << 63) - 1)
        for _ in range(3):
            camera.tick()
        assert camera.frames_captured == 0 and "wrap more than" in (camera.capture_error or "")
        assert caplog.text.count("no frame at these settings") == 1
        camera.settings = replace(camera.settings, gain=1.0, integration_ns=1_000_000)
        camera.tick()
        assert camera.frames_captured == 1 and camera.capture_error is None
    finally:
        draining.set()
        reader.join(5)


def test_a_loop_nobody_reads_refuses_the_write_instead_of_raising() -> None:
    """pyserial's loop holds 4096 bytes; past that its queue.Full used to escape write()."""
    endpoint = LoopEndpoint()
    try:
        assert endpoint.write(bytes(5000)) is False
    finally:
        endpoint.close()


def test_a_pty_link_path_never_replaces_a_users_file(tmp_path) -> None:  # type: ignore[no-untyped-def]
    """``pty:PATH`` naming an existing file (or a file beside it at PATH.new) is refused
    and the file stays; a link left by an earlier run is taken over and removed."""
    for taken in ("precious.txt", "precious.txt.new"):
        (tmp_path / taken).write_text("important data")
        with pytest.raises(InvalidInputError, match="exists and is not a link to a pseudo"):
            open_endpoint(f"pty:{tmp_path / 'precious.txt'}")
        assert (tmp_path / taken).read_text() == "important data"
        (tmp_path / taken).unlink()
    left_over = tmp_path / "scamp5"
    left_over.symlink_to("/dev/pts/999")
    endpoint = open_endpoint(f"pty:{left_over}")
    assert os.readlink(left_over) != "/dev/pts/999"
    endpoint.close()
    assert not os.path.lexists(left_over)


def test_a_running_cameras_pty_link_is_not_taken_over(tmp_path) -> None:  # type: ignore[no-untyped-def]
    """A second simulated camera on the same path re-pointed the link, and removed it on
    exit while the first still ran: its daemon could not reconnect."""
    first = open_endpoint(f"pty:{tmp_path / 'scamp5'}")
    try:
        with pytest.raises(InvalidInputError, match="a simulated camera that is running"):
            open_endpoint(f"pty:{tmp_path / 'scamp5'}")
        assert os.path.exists(tmp_path / "scamp5")
    finally:
        first.close()
