"""The device daemon: read mcam-link v1 from a camera port, publish frames to Redis.

Opens any pyserial URL (``/dev/ttyACM0``, a pty path, ``socket://``,
``rfc2217://``, ``loop://``; checked and opened by :mod:`device.serial_ports`) and
reconnects with exponential backoff when it goes away. Every valid data packet becomes
a :class:`FrameMessage` on ``frames:<device>``; the first frame after a (re)connect or
a sequence gap carries ``discont``. Bracket packets are merged into a reference HDR and
stored as a training pair instead of being streamed. Control commands from
``control:<device>`` are written to the camera as control packets.
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import queue
import select
import threading
from collections import Counter
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import redis
import serial

from device.bracketing import BracketCollector, SaturatedBracketError, save_pair
from device.commands import Command, to_packet
from device.daemon_claim import DaemonClaim
from device.datasets import DatasetLimits, prune_pairs
from device.health import DeviceHealth, unwrap_sequence
from device.link_parser import DROP_CAUSES, LinkParser
from device.link_protocol import DEFAULT_MAX_PAYLOAD, FLAG_BRACKET, DataPacket, encode_control
from device.publisher import FramePublisher
from device.serial_ports import PortOpener, port_problem, serial_opener
from models.errors import McamError
from models.formation import SensorParams
from worker.frame_message import FrameMessage
from worker.redis_keys import DEVICES_SET, health_key, validate_device_id
from worker.redis_memory import TroubleLog

log = logging.getLogger(__name__)

#: Parser drop causes of packets the link damaged (an unknown type or a malformed packet
#: came as the camera sent it).
DAMAGE_CAUSES = ("bad_header", "oversize", "bad_crc", "truncated")
#: Most bytes taken from the port in one read.
MAX_READ = 1 << 20
#: While the port stays closed, a warning every this many failed attempts (about a
#: minute at the longest backoff); the others are logged at debug level.
WARN_EVERY = 30


@dataclass(frozen=True)
class DaemonConfig:
    """Daemon settings. Times in seconds, sizes in bytes or frames."""

    port: str
    device: str
    frames_maxlen: int = 256
    queue_size: int = 64
    max_payload: int = DEFAULT_MAX_PAYLOAD
    read_timeout_s: float = 0.05
    partial_timeout_s: float = 1.0
    backoff_initial_s: float = 0.05
    backoff_max_s: float = 2.0
    data_dir: Path | None = None
    dataset_limits: DatasetLimits = DatasetLimits()


def packet_params(packet: DataPacket) -> SensorParams:
    """The sensor parameters a data packet states (a gain of 0: unknown); a clear error
    for values out of range."""
    return SensorParams.parse({"encoding": packet.encoding, "alpha": packet.alpha,
                               "bits": packet.bits, "gain": packet.gain or None})


def crash_line(crash: Exception) -> str:
    """An unexpected error on one line: its type, and its message if it has one."""
    reason = " ".join(str(crash).split())
    return f"{type(crash).__name__}: {reason}" if reason else type(crash).__name__


class DeviceDaemon:
    """One camera link. :meth:`run` blocks until :meth:`stop`; :meth:`start` uses a thread."""

    def __init__(self, config: DaemonConfig, client: redis.Redis,
                 opener: PortOpener | None = None) -> None:
        self.config = config
        self.client = client
        self.device = validate_device_id(config.device)
        self.health = DeviceHealth(self.device, config.port)
        self.claim = DaemonClaim(client, self.device)
        self.publisher = FramePublisher(client, self.device, self.health, self.send_command,
                                        config.frames_maxlen, config.queue_size, self.claim,
                                        on_failure=self._fail)
        self.opener = opener or serial_opener(config.port, config.read_timeout_s)
        self.brackets = BracketCollector()
        self._parser = self._new_parser()
        self._parser_base: Counter[str] = Counter()
        # Control entries (id, packet; None: refused) for the camera, in order.
        self._outbox: queue.Queue[tuple[str, bytes | None]] = queue.Queue(maxsize=64)
        # An entry whose write failed (the link broke): sent first on the next link.
        self._unsent: tuple[str, bytes | None] | None = None
        self._stop = threading.Event()
        self._finished = threading.Event()
        self._thread: threading.Thread | None = None
        #: Why the daemon stopped on its own (another daemon keeps the device), or None.
        self.failure: McamError | None = None
        #: The unexpected error (a bug) the daemon stopped on, or None (:meth:`run`,
        #: :meth:`FramePublisher.run`).
        self.crash: Exception | None = None
        self._last_sequence: int | None = None
        self._discont = True
        # Packets of bracketed captures since the last streamed frame (sequence numbers
        # the frame stream lacks, but no frames lost).
        self._bracketed = 0
        self._connected_once = False
        self._trouble = TroubleLog(log)

    def _new_parser(self) -> LinkParser:
        return LinkParser(self.config.max_payload, self.config.partial_timeout_s)

    # ---- control ----
    def send_command(self, entry_id: str, command: Command | None) -> bool:
        """Queue control entry ``entry_id``'s command for the camera (None: refused, kept
        in line so that the device's cursor moves past it in order); False, and nothing
        queued, when 64 wait already (the entry stays in Redis until there is room)."""
        packet = None if command is None else encode_control(to_packet(command))
        try:
            self._outbox.put_nowait((entry_id, packet))
        except queue.Full:
            return False
        return True

    def _flush_outbox(self, port: Any) -> None:
        """Write the queued commands to the camera, in order, each then recorded as
        delivered (the device's cursor). A write that fails (a timeout, the link gone)
        keeps its command for the next link, where it goes first; the failure itself
        ends this link."""
        while True:
            if self._unsent is None:
                try:
                    self._unsent = self._outbox.get_nowait()
                except queue.Empty:
                    return
            entry_id, packet = self._unsent
            if packet is not None:
                port.write(packet)
                self.health.add("control_sent")
            self._unsent = None
            self.publisher.delivered(entry_id)

    # ---- frames ----
    def _on_data(self, packet: DataPacket) -> None:
        packet = dataclasses.replace(packet, sequence=self._host_sequence(packet.sequence))
        expected = None if self._last_sequence is None else self._last_sequence + 1
        if expected is not None and packet.sequence != expected:
            self.health.sequence_gap(expected, packet.sequence)
            self._discont = True
            self.brackets.interrupt()
        self._last_sequence = packet.sequence
        if packet.flags & FLAG_BRACKET:
            # A bracket's exposures are not streamed: the settings stay the frames'.
            self.health.frame_received(packet.sequence, None)
            self._bracketed += 1
            self._on_bracket_packet(packet)
            return
        self.health.frame_received(packet.sequence, {
            "encoding": packet.encoding, "alpha": packet.alpha, "bits": packet.bits,
            "gain": packet.gain, "width": int(packet.codes.shape[1]),
            "height": int(packet.codes.shape[0]),
        })
        self.publisher.offer(FrameMessage(self.device, packet.sequence, packet.timestamp_ns,
                                          packet.codes, packet_params(packet), self._discont,
                                          self._bracketed))
        self._discont = False
        self._bracketed = 0

    def _host_sequence(self, sequence: int) -> int:
        """The host's number for the camera's ``sequence``: on from the last frame's (this
        daemon's, or the previous daemon's until this one got a frame), past a wrap of
        the firmware's 32-bit counter (:func:`unwrap_sequence`)."""
        last = self._last_sequence if self._last_sequence is not None else self.health.last_sequence
        return unwrap_sequence(sequence, last + 1) if last >= 0 else sequence

    def _on_bracket_packet(self, packet: DataPacket) -> None:
        bracket = self.brackets.add(packet)
        self.health.set("brackets_incomplete", self.brackets.abandoned)
        if bracket is None or self.config.data_dir is None:
            return
        try:
            folder = save_pair(self.config.data_dir, self.device, bracket)
        except (McamError, OSError) as exc:
            if isinstance(exc, SaturatedBracketError):
                self.health.add("brackets_saturated")
            log.warning("bracket at sequence %d not saved: %s", bracket.wrapped.sequence, exc)
            return
        self.health.add("brackets_saved")
        log.info("bracketed reference pair saved in %s", folder)
        try:
            prune_pairs(self.config.data_dir, self.device, self.config.dataset_limits)
        except OSError as exc:
            log.warning("old dataset pairs of %s not removed: %s", self.device, exc)

    def _feed(self, data: bytes) -> None:
        # A partial packet also expires while bytes keep coming, once complete packets
        # arrive behind it: a corrupt length must not hold them back for long.
        malformed = self._parser.drops["malformed"]
        damaged = self._damaged()
        packets = self._parser.feed(data) if data else []
        packets += self._parser.expire(quiet=not data)
        if self._parser.drops["malformed"] > malformed:
            self._report_malformed()
        for packet in packets:
            if not isinstance(packet, DataPacket):
                continue  # control packets only travel host -> device
            try:
                self._on_data(packet)
            except McamError as exc:
                log.warning("frame %d rejected: %s", packet.sequence, exc.message)
                self.health.add("dropped_rejected")
            except Exception:
                # One packet the daemon cannot handle must not stop the link's reader.
                log.exception("frame %d could not be handled", packet.sequence)
                self.health.add("dropped_rejected")
        self.health.set_parser_counts(self._parser.drops, self._parser.garbage_bytes,
                                      self._parser_base)
        if self._damaged() > damaged:
            self._report_damage()

    def _damaged(self) -> int:
        """Packets the current parser dropped as damaged on the link (:data:`DAMAGE_CAUSES`)."""
        return sum(self._parser.drops[cause] for cause in DAMAGE_CAUSES)

    def _report_damage(self) -> None:
        """Say that the link damages packets, with the device's counts so far, at most
        every 30 s: only the health hash counted them, and a link losing a third of its
        frames to bad checksums and cut packets wrote not a line to the daemon's log."""
        counts = self.health.drop_counts()
        causes = ", ".join(f"{cause} {counts[cause]}" for cause in DAMAGE_CAUSES if counts[cause])
        self._trouble.report(
            f"device {self.device}'s link {self.config.port}",
            f"packets dropped as damaged ({causes} so far; "
            f"{self.health.counts['garbage_bytes']} garbage bytes)",
            then="check the camera's cable, connector and port; the frames are lost "
                 f"(GET /v1/devices/{self.device} counts each cause)",
        )  # fmt: skip

    def _report_malformed(self) -> None:
        """Say why the camera's packets are dropped as malformed (a counter alone did not:
        a camera set to 17 bits or alpha 1 lost every frame without a word), at most
        every 30 s."""
        self._trouble.report(
            f"device {self.device}'s camera",
            f"packets dropped as malformed, the newest because {self._parser.last_malformed}",
            then="fix the camera's settings or firmware (docs/mcam-link-v1.md, section 2)",
        )  # fmt: skip

    # ---- the link ----
    def _open(self) -> Any | None:
        """Open the port, retrying with exponential backoff; None if stopped meanwhile."""
        delay = self.config.backoff_initial_s
        failures = 0
        while not self._stop.is_set():
            try:
                port = self.opener()
            except (serial.SerialException, OSError, ValueError) as exc:
                failures += 1
                self._port_failed(exc, failures)
                self._stop.wait(delay)
                delay = min(delay * 2, self.config.backoff_max_s)
                continue
            if failures:
                log.info("opened %s after %d failed attempts", self.config.port, failures)
            if self._connected_once:
                self.health.add("reconnects")
            self._connected_once = True
            self.health.state = "connected"
            self.health.port_error = ""
            return port
        return None

    def _port_failed(self, exc: Exception, failures: int) -> None:
        """Record why the port did not open; warn on the first failure of an outage and
        then every :data:`WARN_EVERY` attempts, so a wrong ``--port`` is seen at once."""
        reason = port_problem(self.config.port, exc)
        self.health.port_error = reason
        if failures == 1 or failures % WARN_EVERY == 0:
            log.warning(
                "cannot open %s: %s; retrying every %.1f s at most (attempt %d)",
                self.config.port, reason, self.config.backoff_max_s, failures,
            )
        else:
            log.debug("cannot open %s: %s", self.config.port, reason)

    def _pump(self, port: Any) -> None:
        """Read the open port until it fails or the daemon stops."""
        while not self._stop.is_set():
            self._flush_outbox(port)
            self._feed(self._read_chunk(port))

    def _read_chunk(self, port: Any) -> bytes:
        """What the port has now, waiting up to the read timeout for the first byte."""
        if port.timeout == 0:
            select.select([port.fileno()], [], [], self.config.read_timeout_s)
            return bytes(port.read(MAX_READ))
        return bytes(port.read(min(max(port.in_waiting, 1), MAX_READ)))

    def _link_lost(self) -> None:
        """Forget partial packets: the next frame starts a new run (discont). It is still
        seen against the last sequence before the link was lost, so frames the camera sent
        meanwhile are a gap (:meth:`DeviceHealth.sequence_gap`)."""
        self._parser.reset()
        self._parser_base.update({cause: self._parser.drops[cause] for cause in DROP_CAUSES})
        self._parser_base["garbage_bytes"] += self._parser.garbage_bytes
        self._parser = self._new_parser()
        self._discont = True
        self.brackets.interrupt()
        self.health.state = "disconnected"

    def run(self) -> None:
        """Read, parse and publish until :meth:`stop`, reconnecting as needed. An error
        the link's loops do not expect (a bug) ends it as a stop does, logged once with
        its traceback and kept in :attr:`crash`: it went to threading's excepthook, and
        ``mcam device`` exited 0 as if stopped, so nothing restarted it."""
        self.publisher.start()
        try:
            self._serve_links()
        except Exception as exc:
            log.exception("device %s: the daemon stopped on an unexpected error; %s is no "
                          "longer read", self.device, self.config.port)
            self.crash = exc
        finally:
            self._end()

    def _end(self) -> None:
        """Publish what is queued, the publisher's last health write saying the daemon
        stopped or crashed; after a crash (also one in that last write) say so from this
        thread too (:meth:`_report_crash`); release the claim, and end :meth:`wait`."""
        if self.crash is None:
            self.health.state = "stopped"
        else:
            self.health.crashed(crash_line(self.crash))
        self.publisher.stop()
        if self.crash is not None:
            self._report_crash(self.crash)
        with contextlib.suppress(redis.RedisError, OSError):
            self.claim.release()
        self._finished.set()

    def _report_crash(self, crash: Exception) -> None:
        """Say in the device's health that the daemon crashed, and on what: the publishing
        thread, which writes the health, may be the one that died, and the device then
        read ``connected`` for good. Written while this daemon holds the device's claim
        (another daemon's health is not touched): the crash's fields over the health this
        daemon or its predecessor last wrote, or, with none, all of this daemon's; but
        none once this daemon's health was written and is gone: the device was forgotten
        (``DELETE /v1/devices/{id}`` takes a crashed one at once) after the publisher's
        last write, and writing would register it again. Redis errors are logged (the
        crash itself is already)."""
        fields = self.health.crashed(crash_line(crash))
        key = health_key(self.device)
        try:
            if not self.claim.renew():
                return
            with self.client.pipeline() as pipe:
                pipe.watch(key)  # a forget in between: not written (WatchError)
                if not pipe.exists(key):
                    if self.publisher.health_written:
                        return
                    fields = {**self.health.to_fields(), **fields}
                pipe.multi()
                pipe.hset(key, mapping=fields)
                pipe.sadd(DEVICES_SET, self.device)
                pipe.execute()
        except redis.WatchError:
            return
        except (redis.RedisError, OSError) as exc:
            log.warning("device %s: its health could not be marked crashed: %s",
                        self.device, exc)

    def _serve_links(self) -> None:
        """Open the port and read it, again after each link lost, until :meth:`stop`."""
        while not self._stop.is_set():
            port = self._open()
            if port is None:
                return
            try:
                self._pump(port)
            except (serial.SerialException, OSError) as exc:
                log.warning("link %s lost: %s", self.config.port, exc)
            finally:
                with contextlib.suppress(Exception):
                    port.close()
                self._link_lost()

    def _fail(self, error: Exception) -> None:
        """Stop on the publisher's failure: another daemon holds the device's claim
        (:attr:`failure`), or an unexpected error (a bug, logged: :attr:`crash`)."""
        if isinstance(error, McamError):
            self.failure = error
        else:
            self.crash = error
        self._stop.set()

    def start(self) -> DeviceDaemon:
        """Run in a daemon thread."""
        self._thread = threading.Thread(target=self.run, name=f"daemon-{self.device}",
                                        daemon=True)
        self._thread.start()
        return self

    def request_stop(self) -> None:
        """Ask :meth:`run` to stop (safe in a signal handler); :meth:`wait` for it."""
        self._stop.set()

    def wait(self, timeout_s: float | None = None) -> bool:
        """Wait until :meth:`run` has ended (stopped, :attr:`failure` or :attr:`crash`);
        True if it has."""
        return self._finished.wait(timeout_s)

    def stop(self, timeout_s: float = 10.0) -> None:
        """Stop reading, publish what is queued, close the port."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=timeout_s)
