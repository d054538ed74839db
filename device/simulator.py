"""A virtual SCAMP-5: renders a scene sequence, encodes it in-pixel, streams mcam-link v1.

Every frame goes through :func:`models.formation.simulate` (modulo by default,
like the prototype; mantissa or clip on request) with shot and read noise,
seeded per sequence number so :meth:`VirtualScamp5.ground_truth` re-renders
exactly what was sent. Control packets from the host change the settings,
start/stop the stream, or trigger a bracketed reference capture: one packet of
the wrapped frame (bracket index 0) and ``count`` clipped images whose gain
doubles (by ``ratio``) each time, all of the same scene instant.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import OrderedDict
from dataclasses import dataclass, replace

from device.commands import (
    BracketCommand,
    Command,
    EncodingCommand,
    ExposureCommand,
    FrameRateCommand,
    StartCommand,
    StopCommand,
    to_command,
)
from device.faults import Faults
from device.link_parser import LinkParser
from device.link_protocol import (
    FLAG_BRACKET,
    REFERENCE_INTEGRATION_NS,
    DataPacket,
    encode_data,
)
from device.scenes import ProceduralScene, SceneSequence
from device.sim_link import Endpoint
from models.errors import InvalidInputError, McamError
from models.formation import MAX_NOISE_SEED, SensorFrame, SensorParams, simulate

log = logging.getLogger(__name__)

#: A frame's noise seed is ``seed * SEED_STRIDE + sequence`` (recorded frames rely on it).
SEED_STRIDE = 1_000_003
#: Sequence numbers a camera seed leaves room for: 2**40 frames, over three years at
#: 10 000 frames per second.
SEQUENCE_ROOM = 1 << 40
#: Largest camera seed: every frame's noise seed up to ``SEQUENCE_ROOM`` fits an int64.
MAX_SEED = (MAX_NOISE_SEED - SEQUENCE_ROOM) // SEED_STRIDE
#: Longest the streaming thread waits between frames without reading control input (s).
CONTROL_POLL_S = 0.05


@dataclass(frozen=True)
class CameraSettings:
    """What the host can change: encoding, exposure, frame rate, streaming on/off."""

    encoding: str = "modulo"
    alpha: float = 2.0
    bits: int = 8
    gain: float = 1.0
    integration_ns: int = REFERENCE_INTEGRATION_NS
    fps: float = 30.0
    running: bool = True
    read_noise: float = 0.002
    full_well: float | None = 20_000.0

    @property
    def exposure_gain(self) -> float:
        """Wrap units per scene unit: analog gain x integration / reference integration."""
        return self.gain * self.integration_ns / REFERENCE_INTEGRATION_NS


@dataclass(frozen=True)
class SentFrame:
    """What the device did with one sequence number (for tests and benches)."""

    index: int
    params: SensorParams
    intact: bool
    bracket_index: int = 0
    bracket_count: int = 0


class VirtualScamp5:
    """The virtual camera. Call :meth:`step` yourself, or :meth:`start` a streaming thread.

    ``history``: how many sent sequence numbers to remember for
    :meth:`ground_truth` (0 keeps none); ``seed``: 0 to :data:`MAX_SEED`.
    """

    def __init__(self, endpoint: Endpoint, scene: SceneSequence | None = None,
                 settings: CameraSettings | None = None, faults: Faults | None = None,
                 seed: int = 0, history: int = 0, max_frames: int | None = None) -> None:
        self.endpoint = endpoint
        self.scene = scene if scene is not None else ProceduralScene()
        self.settings = settings or CameraSettings()
        self.faults = faults or Faults()
        if not 0 <= seed <= MAX_SEED:
            raise InvalidInputError(
                f"seed must be from 0 to {MAX_SEED} (a frame's noise seed, seed x {SEED_STRIDE}"
                f" + sequence, must fit an int64), got {seed}"
            )
        self.seed = seed
        self.max_frames = max_frames
        self.sequence = 0
        self.frame_index = 0
        self.frames_captured = 0
        self.capture_error: str | None = None  # why the last tick formed no frame
        self.packets_sent = 0
        self.packets_unsent = 0
        self.sent: OrderedDict[int, SentFrame] = OrderedDict()
        self._history = history
        self._bracket: BracketCommand | None = None
        self._parser = LinkParser(max_payload=64)
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.lock = threading.Lock()

    # ---- rendering ----
    def params_for(self, sequence: int, encoding: str | None = None,
                   gain: float | None = None) -> SensorParams:
        """Sensor parameters (noise seeded by ``sequence``) for the current settings."""
        s = self.settings
        return SensorParams.parse({
            "encoding": encoding or s.encoding, "alpha": s.alpha, "bits": s.bits,
            "gain": gain if gain is not None else s.exposure_gain,
            "read_noise": s.read_noise, "full_well": s.full_well,
            "seed": self.seed * SEED_STRIDE + sequence,
        })

    def render(self, index: int, params: SensorParams) -> SensorFrame:
        """The frame the sensor produces for scene ``index`` with ``params``."""
        return simulate(self.scene.render(index), params)

    def ground_truth(self, sequence: int) -> SensorFrame:
        """Re-render the frame sent as ``sequence`` (needs ``history``)."""
        record = self.sent.get(sequence)
        if record is None:
            raise InvalidInputError(f"sequence {sequence} is not in the simulator's history")
        return self.render(record.index, record.params)

    # ---- control ----
    def handle_input(self) -> None:
        """Read host -> device bytes and obey every valid control packet in them."""
        for packet in self._parser.feed(self.endpoint.read()):
            if isinstance(packet, DataPacket):
                continue  # a host does not send images
            try:
                command = to_command(packet)
            except InvalidInputError:
                continue  # out-of-range values: a device ignores the packet
            self.apply(command)

    def apply(self, command: Command) -> None:
        """Change the settings as a validated control command asks."""
        s = self.settings
        match command:
            case StartCommand():
                s = replace(s, running=True)
            case StopCommand():
                s = replace(s, running=False)
            case ExposureCommand():
                s = replace(s, gain=command.gain, integration_ns=command.integration_ns)
            case EncodingCommand():
                s = replace(s, encoding=command.encoding, bits=command.bits, alpha=command.alpha)
            case FrameRateCommand():
                s = replace(s, fps=command.fps)
            case BracketCommand():
                self._bracket = command
        self.settings = s

    # ---- sending ----
    def _send(self, packet: DataPacket, record: SentFrame) -> None:
        data, intact = self.faults.apply(encode_data(packet))
        count = self.packets_sent + self.packets_unsent
        if self.faults.disconnect_now(count):
            self.endpoint.disconnect()
            time.sleep(self.faults.disconnect_s)
            self.endpoint.reconnect()
        if self.faults.stall_now(count) and data:
            half = len(data) // 2
            delivered = self.endpoint.write(data[:half])
            time.sleep(self.faults.stall_s)
            delivered = self.endpoint.write(data[half:]) and delivered
        else:
            delivered = self.endpoint.write(data) if data else True
        if delivered:
            self.packets_sent += 1
        else:
            self.packets_unsent += 1
        if self._history:
            self.sent[packet.sequence] = replace(record, intact=intact and delivered)
            while len(self.sent) > self._history:
                self.sent.popitem(last=False)

    def _capture(self, params: SensorParams, flags: int = 0, bracket_index: int = 0,
                  bracket_count: int = 0) -> None:
        frame = self.render(self.frame_index, params)
        packet = DataPacket(
            sequence=self.sequence, timestamp_ns=time.monotonic_ns(), encoding=params.encoding,
            alpha=params.alpha, bits=params.bits, gain=float(params.gain or 0.0),
            codes=frame.codes, flags=flags, bracket_index=bracket_index,
            bracket_count=bracket_count,
        )
        record = SentFrame(self.frame_index, params, True, bracket_index, bracket_count)
        self._send(packet, record)
        self.sequence += 1

    def capture_frame(self) -> None:
        """Expose, encode and send one frame, then advance the scene."""
        self._capture(self.params_for(self.sequence))
        self.frame_index += 1
        self.frames_captured += 1

    def capture_bracket(self, command: BracketCommand) -> None:
        """Send the wrapped frame and ``count`` clipped exposures of the current scene."""
        gain = self.settings.exposure_gain
        base = command.base_gain or gain / command.ratio ** (command.count - 1)
        total = command.count + 1
        self._capture(self.params_for(self.sequence), FLAG_BRACKET, 0, total)
        for i in range(command.count):
            params = self.params_for(self.sequence, "clip", base * command.ratio**i)
            self._capture(params, FLAG_BRACKET, i + 1, total)
        self.frame_index += 1

    def step(self) -> None:
        """One tick: obey control input, then capture a bracket or a frame if running."""
        with self.lock:
            self.handle_input()
            if self._bracket is not None:
                command, self._bracket = self._bracket, None
                self.capture_bracket(command)
            elif self.settings.running and not self.done():
                self.capture_frame()

    # ---- streaming thread ----
    def done(self) -> bool:
        """Whether ``max_frames`` regular frames have been captured."""
        return self.max_frames is not None and self.frames_captured >= self.max_frames

    def tick(self) -> None:
        """:meth:`step`, surviving settings under which no frame can be formed (an
        exposure whose pixels would wrap more than int64 counts): the camera logs it once
        and sends nothing until a command changes them, as a sensor that saturates its
        counters would, instead of its thread dying with the link still open."""
        try:
            self.step()
        except McamError as exc:
            if exc.message != self.capture_error:
                log.warning("virtual camera: no frame at these settings: %s", exc.message)
            self.capture_error = exc.message
        else:
            self.capture_error = None

    def run(self) -> None:
        """Tick at the set frame rate until :meth:`stop`."""
        due = time.monotonic()
        while not self._stop.is_set():
            self.tick()
            due = self.wait_for_next_frame(due)

    def wait_for_next_frame(self, last_due: float) -> float:
        """Wait one frame period (at the current fps) after ``last_due`` (monotonic s),
        reading control input every ``CONTROL_POLL_S``, so that a new frame rate counts
        from ``last_due`` at once; return when the next frame is due (also on :meth:`stop`)."""
        while True:
            due = max(last_due + 1.0 / self.settings.fps, time.monotonic() - 0.1)
            remaining = due - time.monotonic()
            if remaining <= 0 or self._stop.wait(min(remaining, CONTROL_POLL_S)):
                return due
            with self.lock:
                self.handle_input()

    def start(self) -> VirtualScamp5:
        """Run :meth:`run` in a daemon thread."""
        self._thread = threading.Thread(target=self.run, name="virtual-scamp5", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        """Stop the thread and close the link."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=5)
        self.endpoint.close()
