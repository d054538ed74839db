"""The device daemon: read mcam-link v1 from a camera port, publish frames to Redis.

Opens any pyserial URL (``/dev/ttyACM0``, a pty path, ``socket://``,
``rfc2217://``, ``loop://``) and reconnects with exponential backoff when it
goes away. Every valid data packet becomes a :class:`FrameMessage` on
``frames:<device>``; the first frame after a (re)connect or a sequence gap
carries ``discont``. Bracket packets are merged into a reference HDR and stored
as a training pair instead of being streamed. Control commands from
``control:<device>`` are written to the camera as control packets.
"""

from __future__ import annotations

import contextlib
import dataclasses
import errno
import importlib
import logging
import os
import queue
import re
import select
import stat
import threading
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any
from urllib.parse import parse_qs, urlsplit

import redis
import serial
import serial.rfc2217

from device.bracketing import BracketCollector, SaturatedBracketError, save_pair
from device.commands import Command, to_packet
from device.daemon_claim import DaemonClaim
from device.datasets import DatasetLimits, prune_pairs
from device.health import DeviceHealth, unwrap_sequence
from device.link_parser import DROP_CAUSES, LinkParser
from device.link_protocol import DEFAULT_MAX_PAYLOAD, FLAG_BRACKET, DataPacket, encode_control
from device.publisher import FramePublisher
from device.sim_link import MAX_TCP_PORT
from models.errors import InvalidInputError, McamError
from models.formation import SensorParams
from worker.frame_message import FrameMessage
from worker.redis_keys import DEVICES_SET, health_key, validate_device_id
from worker.redis_memory import TroubleLog

log = logging.getLogger(__name__)

PortOpener = Callable[[], Any]
#: Port URL schemes that name a host and a TCP port.
NETWORK_SCHEMES = ("socket", "rfc2217")
#: Port URL schemes whose options pyserial reads without opening anything
#: (:func:`check_url_options`).
PARSED_SCHEMES = ("loop", "socket", "rfc2217", "alt")
#: Options of pyserial's ``spy://`` URLs that take no value (``file=PATH`` takes one).
SPY_FLAGS = ("color", "raw", "all")
#: Parser drop causes of packets the link damaged (an unknown type or a malformed packet
#: came as the camera sent it).
DAMAGE_CAUSES = ("bad_header", "oversize", "bad_crc", "truncated")
#: What pyserial's ``rfc2217://`` open says when the server did not negotiate RFC 2217
#: (Telnet binary mode and the COM port option) within its timeout.
RFC2217_UNANSWERED = "Remote does not seem to support RFC2217"
#: Most seconds an ``rfc2217://`` URL's ``timeout`` may give the server to answer: a stop
#: waits for an open in progress, which negotiation bounds by it.
MAX_RFC2217_TIMEOUT_S = 60.0
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


def check_port_url(url: str) -> None:
    """Refuse an empty port, a port URL whose scheme pyserial does not know, a network
    one without a host and port (:func:`check_host_port`), a ``spy://`` one without a
    device path (:func:`check_spy_port`), or options pyserial refuses
    (:func:`check_url_options`, :func:`check_spy_options`, :func:`check_hwgrep_url`):
    retrying could never open them, unlike a tty that is not plugged in yet."""
    if not url.strip():
        raise InvalidInputError(
            "the port is empty; give a device path (/dev/ttyACM0), socket://HOST:PORT or "
            "rfc2217://HOST:PORT"
        )
    scheme, separator, _ = url.partition("://")
    if separator:
        check_scheme(url, scheme)
    if scheme in NETWORK_SCHEMES:
        check_host_port(url, scheme)
    if scheme in PARSED_SCHEMES and "?" in url:
        check_url_options(url, scheme)
    if scheme == "spy":
        check_spy_port(url)
        check_spy_options(url)
    if scheme == "hwgrep":
        check_hwgrep_url(url)


def check_url_options(url: str, scheme: str) -> None:
    """Refuse a port URL whose options (``?logging=...``, ``?class=...``) pyserial
    refuses, as it would at every open: ``loop://?logging=DEBUG`` stopped the daemon with
    a bare KeyError traceback (exit 0), ``socket://HOST:PORT?logging=bogus`` was retried
    for good with "'bogus'", as was ``alt://PATH?class=Nope`` with "unknown class:
    'Nope'", and ``alt://PATH?class=XON`` (a constant of pyserial's, not a class) stopped
    the daemon on a TypeError. pyserial's own parser (``from_url`` of an unopened port,
    alt://'s ``serial_class_for_url``) reads them; with a valid ``logging`` it sets up
    logging as the open would."""
    handler = importlib.import_module(f"serial.urlhandler.protocol_{scheme}")
    try:
        if scheme == "alt":
            handler.serial_class_for_url(url)
        else:
            handler.Serial().from_url(url)
    except (serial.SerialException, ValueError, KeyError, TypeError) as exc:
        # A KeyError's or TypeError's text is no reason: an unknown level, pyserial's own
        # message failing to format ('debug|info|warning|error' for loop://?baud=9600), or
        # its class check failing ('issubclass() arg 1 must be a class').
        reason = "" if isinstance(exc, KeyError | TypeError) else f" ({exc})"
        raise InvalidInputError(
            f"bad option in port URL {url!r}{reason}; {url_options(scheme)}"
        ) from None
    if scheme == "rfc2217":
        check_rfc2217_timeout(url)


def check_spy_port(url: str) -> None:
    """Refuse a ``spy://`` URL without the device path of the port to watch, or with a
    port URL in its place (pyserial's spy:// watches device paths only): every open
    failed with "could not open port : [Errno 2] No such file or directory: ''" (or the
    URL in its place), retried for good."""
    parts = urlsplit(url)
    port = parts.netloc + parts.path  # what pyserial opens
    scheme, separator, _ = port.partition("://")
    if port and not separator:
        return
    problem = f"pyserial's spy:// cannot watch {scheme}:// ports" if separator else (
        "it names no port")
    raise InvalidInputError(
        f"bad port URL {url!r}: {problem}; give spy:// the device path of the port to "
        "watch, as in spy:///dev/ttyACM0"
    )


def check_spy_options(url: str) -> None:
    """Refuse a ``spy://`` URL's options that pyserial refuses at every open: an unknown
    one (``spy:///dev/ttyACM0?bogus=1`` was retried for good with "expected a string in
    the form ...: unknown option: 'bogus'"), or a ``file`` that cannot be created (no
    name, a directory, or in a directory that does not exist: retried for good with "No
    such file or directory"). Read as pyserial reads them, but without opening the file:
    pyserial's parser opens it for writing, emptying it."""
    for option, values in parse_qs(urlsplit(url).query, keep_blank_values=True).items():
        if option == "file":
            check_spy_file(url, values[0])  # pyserial takes the first
        elif option not in SPY_FLAGS:
            raise InvalidInputError(f"bad option in port URL {url!r} (unknown option: "
                                    f"{option!r}); {url_options('spy')}")


def check_spy_file(url: str, path: str) -> None:
    """Refuse a ``spy://`` URL's ``file`` (where pyserial writes the traffic it sees) that
    no open could create: empty, a directory, or in a directory that does not exist."""
    folder = os.path.dirname(path) or "."
    if not path:
        problem = "names no file"
    elif os.path.isdir(path):
        problem = "is a directory"
    elif not os.path.isdir(folder):
        problem = f"is in {folder}, which is no directory"
    else:
        return
    raise InvalidInputError(
        f"bad option in port URL {url!r}: file={path} {problem}; give ?file= a file in an "
        "existing directory (spy:// writes the traffic it sees there), or leave it out "
        "(standard error)"
    )


def check_hwgrep_url(url: str) -> None:
    """Refuse a ``hwgrep://REGEXP&OPTION...`` URL that pyserial refuses at every open: an
    unknown option, or an ``n`` that is no whole number from 2 (retried for good with
    "unknown option: 'bogus'"), an ``n`` with no value or a REGEXP that does not compile
    (a TypeError or re.error, which stopped ``mcam device`` as a bug: exit 1, "please
    report it"). Read as pyserial reads it (options follow ``&``: a ``?`` is the
    regexp's), without looking for ports."""
    regexp, *options = url[len("hwgrep://"):].split("&")
    try:
        re.compile(regexp, re.IGNORECASE)
    except re.error as exc:
        raise InvalidInputError(
            f"bad port URL {url!r}: {regexp!r} is no regular expression ({exc}); give "
            "hwgrep://REGEXP, a Python regular expression that matches the camera's port "
            "name, description or hardware id (python -m serial.tools.list_ports -v lists "
            "them)"
        ) from None
    for option in options:
        name, equals, value = option.partition("=")
        if name == "skip_busy" or (name == "n" and equals and _from_2(value)):
            continue
        raise InvalidInputError(
            f"bad option {option!r} in port URL {url!r}; {url_options('hwgrep')}"
        )


def _from_2(value: str) -> bool:
    """Whether hwgrep://'s ``n`` takes ``value``: a whole number from 2 (pyserial's
    "numbering starts at 1" refuses 1)."""
    try:
        return int(value) >= 2
    except ValueError:
        return False


def url_options(scheme: str) -> str:
    """What options a :data:`PARSED_SCHEMES`, ``spy://`` or ``hwgrep://`` port URL takes,
    for an error message."""
    if scheme == "hwgrep":
        return ("pyserial's hwgrep:// takes &n=N (the Nth port that matches, N from 2; the "
                "first without it) and &skip_busy, or none")
    if scheme == "spy":
        return (f"pyserial's spy:// takes ?file=PATH (where it writes the traffic it sees; "
                f"standard error without it), {', '.join(SPY_FLAGS)}, or none")
    if scheme == "alt":
        classes = sorted(name for name, value in vars(serial).items()
                         if isinstance(value, type) and issubclass(value, serial.Serial))
        return f"pyserial's alt:// takes ?class= one of {', '.join(classes)}, or none"
    return (f"pyserial's {scheme}:// takes ?logging=debug, info, warning or error "
            "(rfc2217:// also ign_set_control, poll_modem and timeout=SECONDS), or none")


def check_rfc2217_timeout(url: str) -> None:
    """Refuse an ``rfc2217://`` URL's ``timeout`` (seconds the server has to answer
    negotiation and each control request) that is not above 0 and at most
    :data:`MAX_RFC2217_TIMEOUT_S`: pyserial takes any float, and at 0 or below (or nan)
    every open failed as unanswered ("did not answer ... in time", retried for good),
    while inf never ends the wait for a server that does not negotiate (nor a stop
    meanwhile). pyserial reads the first value given."""
    values = parse_qs(urlsplit(url).query, keep_blank_values=True).get("timeout")
    if not values:
        return
    timeout_s = float(values[0])  # a number: pyserial's parser took it
    if not 0 < timeout_s <= MAX_RFC2217_TIMEOUT_S:
        raise InvalidInputError(
            f"bad option in port URL {url!r}: timeout={values[0]} is out of range; give "
            f"?timeout=SECONDS above 0 and at most {MAX_RFC2217_TIMEOUT_S:g} (how long the "
            "RFC 2217 server has to answer; 3 without it), or leave it out"
        )


def check_scheme(url: str, scheme: str) -> None:
    """Refuse a port URL scheme pyserial has no handler for, or whose handler cannot load
    (a module it needs is not installed: pyserial then said "protocol 'cp2110' not known"
    at every open, retried for good). A scheme with a dot or another character no module
    name has (``my.host://``) stopped ``mcam device`` with a ModuleNotFoundError
    traceback."""
    module = f"serial.urlhandler.protocol_{scheme}"
    unknown = InvalidInputError(
        f"pyserial does not know the port URL scheme {scheme!r} ({url}); use a device "
        "path (/dev/ttyACM0), socket://HOST:PORT, rfc2217://HOST:PORT or loop://"
    )
    if not scheme.isidentifier():
        raise unknown
    try:
        importlib.import_module(module)
    except ModuleNotFoundError as exc:
        if exc.name == module:
            raise unknown from None
        raise InvalidInputError(
            f"pyserial's {scheme}:// ports need the Python module {exc.name!r}, which is "
            f"not installed ({url}): install it, or use a device path (/dev/ttyACM0)"
        ) from None


def check_host_port(url: str, scheme: str) -> None:
    """Refuse a network port URL without a host, or without a port from 1 to 65535:
    pyserial said "'<=' not supported between instances of 'int' and 'NoneType'" or
    "'debug|info|warning|error'", and the daemon retried it for good."""
    parts = urlsplit(url)
    try:
        port = parts.port
    except ValueError:  # not a number, or beyond 65535
        port = None
    if not parts.hostname or not port:
        raise InvalidInputError(
            f"bad port URL {url!r}: use {scheme}://HOST:PORT with a host and a PORT from 1 "
            f"to {MAX_TCP_PORT}"
        )


def port_problem(url: str, exc: Exception) -> str:
    """Why the port at ``url`` did not open. For a device path where nothing is (no
    directory, no file, a link to nothing) or something that is not a terminal (a
    directory, a regular file, a disk, /dev/null), that and what to do: pyserial said
    only 'No such file or directory', naming the path three times, or 'Could not
    configure port: (25, 'Inappropriate ioctl for device')' ('(22, 'Invalid argument')'
    for a disk), naming none. A port another daemon has open (locked) says so."""
    if url.startswith("rfc2217://") and RFC2217_UNANSWERED in str(exc):
        return rfc2217_unanswered(url)
    if "://" in url:
        return str(exc) or type(exc).__name__
    if not os.path.exists(url):
        return (f"{_missing(Path(url))}: check --port, or plug the camera in or start "
                "mcam simulate-device (it prints the path to give)")
    if getattr(exc, "errno", None) == errno.EWOULDBLOCK:  # the exclusive lock is taken
        return (f"{url} is open in another process that locked it (another mcam device "
                "on this camera?): stop that one, or check --port; this daemon takes the "
                "port once it is free")
    kind = _not_a_terminal(url)
    if kind is None:
        return str(exc) or type(exc).__name__
    return (f"{url} is {kind}, not a serial port: check --port (a camera is a terminal "
            "device such as /dev/ttyACM0; mcam simulate-device prints the path to give)")


def rfc2217_unanswered(url: str) -> str:
    """Why an ``rfc2217://`` port at a server that did not negotiate RFC 2217 did not
    open, and what to do: pyserial said "Remote does not seem to support RFC2217 or
    BINARY mode [we-BINARY:False(INACTIVE), we-RFC2217:False(REQUESTED)]"."""
    address = url.partition("://")[2].partition("?")[0]
    return (
        f"the server at {address} did not answer RFC 2217 negotiation (Telnet binary mode "
        "and COM port control) in time: it is no RFC 2217 server, or not the camera's; "
        f"check the address, or give socket://{address} for a server that passes the "
        "camera's bytes as they are (a raw TCP serial server, mcam simulate-device "
        "--port socket://...), or the camera's serial port (/dev/ttyACM0)"
    )


def _not_a_terminal(path: str) -> str | None:
    """What ``path`` is when it is plainly no terminal (None when it may be one: a
    character device that opens as a tty, or one that cannot be looked at)."""
    try:
        mode = os.stat(path).st_mode
    except OSError:
        return None
    kinds = ((stat.S_ISDIR, "a directory"), (stat.S_ISREG, "a regular file"),
             (stat.S_ISFIFO, "a named pipe"), (stat.S_ISSOCK, "a socket file"),
             (stat.S_ISBLK, "a block device (a disk)"))  # fmt: skip
    for test, kind in kinds:
        if test(mode):
            return kind
    if stat.S_ISCHR(mode) and not _is_tty(path):
        return "a character device that is not a terminal"
    return None


def _is_tty(path: str) -> bool:
    """Whether the character device at ``path`` is a terminal (True when it cannot be
    opened to tell: the port's own error says why)."""
    try:
        descriptor = os.open(path, os.O_RDONLY | os.O_NONBLOCK | os.O_NOCTTY)
    except OSError:
        return True
    try:
        return os.isatty(descriptor)
    finally:
        os.close(descriptor)


def _missing(path: Path) -> str:
    """What is missing of ``path``, which does not exist. os.path, as it never raises
    (Path.exists raises under a directory the daemon may not search)."""
    if not os.path.exists(path.parent):
        return f"directory {path.parent} does not exist"
    with contextlib.suppress(OSError):  # not a link (or no longer one)
        return f"{path} is a link to {os.readlink(path)}, which does not exist"
    return f"{path} does not exist"


def serial_opener(url: str, read_timeout_s: float) -> PortOpener:
    """Open ``url`` with pyserial (any URL :func:`serial.serial_for_url` knows).

    ``socket://`` ports are opened non-blocking (timeout 0): their ``in_waiting`` only
    says whether data is there, not how much, so the reader waits with ``select``
    and then takes everything available in one read. A device path is locked while
    open (``exclusive``): two daemons reading one camera each got a share of its bytes,
    and lost most frames as garbage, with pyserial's 'multiple access on port?'.
    A write gives up after 1 s, but on an ``rfc2217://`` port (:class:`Rfc2217Port`),
    which pyserial opens only without a write timeout (else NotImplementedError, at
    every open): there its socket's own 5 s timeout bounds a write.
    """
    check_port_url(url)
    if url.startswith("rfc2217://"):
        return lambda: Rfc2217Port(url, timeout=read_timeout_s, exclusive=True)
    timeout = 0 if url.startswith("socket://") else read_timeout_s
    return lambda: serial.serial_for_url(url, timeout=timeout, write_timeout=1.0,
                                         exclusive=True)


class Rfc2217Port(serial.rfc2217.Serial):
    """pyserial's ``rfc2217://`` port, whose reader thread ends the link, instead of
    dying with a traceback, on bytes its Telnet parser cannot take: a server that does
    not speak RFC 2217 and sends something (an IAC SE outside a subnegotiation raised
    TypeError) printed "Exception in thread pySerial RFC 2217 reader thread" and a
    traceback at every attempt. The open then fails as unanswered negotiation does
    (:func:`rfc2217_unanswered`); an open link is lost as when the server goes away."""

    def _telnet_read_loop(self) -> None:
        try:
            super()._telnet_read_loop()
        except Exception as exc:  # pyserial's parser, on bytes that are not Telnet
            log.debug("%s: reader ended on bytes that are not Telnet: %r", self.portstr, exc)
            self._read_buffer.put(None)


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
            self._on_bracket_packet(packet)
            return
        self.health.frame_received(packet.sequence, {
            "encoding": packet.encoding, "alpha": packet.alpha, "bits": packet.bits,
            "gain": packet.gain, "width": int(packet.codes.shape[1]),
            "height": int(packet.codes.shape[0]),
        })
        self.publisher.offer(FrameMessage(self.device, packet.sequence, packet.timestamp_ns,
                                          packet.codes, packet_params(packet), self._discont))
        self._discont = False

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
        daemon or its predecessor last wrote, or, with none, all of this daemon's. Redis
        errors are logged (the crash itself is already)."""
        fields = self.health.crashed(crash_line(crash))
        key = health_key(self.device)
        try:
            if not self.claim.renew():
                return
            if not self.client.exists(key):
                fields = {**self.health.to_fields(), **fields}
            pipe = self.client.pipeline(transaction=False)
            pipe.hset(key, mapping=fields)
            pipe.sadd(DEVICES_SET, self.device)
            pipe.execute()
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
