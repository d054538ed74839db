"""The camera port: check a port URL up front, open it, and say why it did not open.

The daemon opens any pyserial URL (``/dev/ttyACM0``, a pty path, ``socket://``,
``rfc2217://``, ``loop://``, ``spy://``, ``hwgrep://``, ``alt://``; a scheme in any case,
as pyserial reads it: :func:`url_scheme`). A URL that no open
could ever take (an unknown scheme, a network one without a host and port, options
pyserial refuses) is refused with :class:`InvalidInputError` before the first open
(:func:`check_port_url`), as retrying it would never succeed; a port that does not open
yet (a tty not plugged in, a server not up) is retried by the daemon, with the reason
:func:`port_problem` gives.
"""

from __future__ import annotations

import contextlib
import errno
import importlib
import logging
import os
import re
import stat
from collections.abc import Callable
from pathlib import Path
from typing import Any
from urllib.parse import parse_qs, urlsplit

import serial
import serial.rfc2217

from device.sim_link import MAX_TCP_PORT
from models.errors import InvalidInputError

log = logging.getLogger(__name__)

PortOpener = Callable[[], Any]
#: Port URL schemes that name a host and a TCP port.
NETWORK_SCHEMES = ("socket", "rfc2217")
#: Port URL schemes whose options pyserial reads without opening anything
#: (:func:`check_url_options`).
PARSED_SCHEMES = ("loop", "socket", "rfc2217", "alt")
#: Options of pyserial's ``spy://`` URLs that take no value (``file=PATH`` takes one).
SPY_FLAGS = ("color", "raw", "all")
#: What pyserial's ``rfc2217://`` open says when the server did not negotiate RFC 2217
#: (Telnet binary mode and the COM port option) within its timeout.
RFC2217_UNANSWERED = "Remote does not seem to support RFC2217"
#: Most seconds an ``rfc2217://`` URL's ``timeout`` may give the server to answer: a stop
#: waits for an open in progress, which negotiation bounds by it.
MAX_RFC2217_TIMEOUT_S = 60.0


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
    scheme = url_scheme(url)
    if scheme is not None:
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


def url_scheme(url: str) -> str | None:
    """The scheme of the port URL ``url`` in lower case, as pyserial reads it
    (``SOCKET://`` and ``socket://`` are one scheme); None for a device path."""
    scheme, separator, _ = url.partition("://")
    return scheme.lower() if separator else None


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
    no open could create: empty, holding a NUL, a directory, or in a directory that does
    not exist."""
    folder = os.path.dirname(path) or "."
    if not path:
        problem = "names no file"
    elif "\x00" in path:
        problem = "holds a NUL character, which no file name can"
    elif os.path.isdir(path):
        problem = "is a directory"
    elif not os.path.isdir(folder):
        problem = f"is in {folder}, which is no directory"
    else:
        return
    raise InvalidInputError(
        f"bad option in port URL {url!r}: file={path.replace(chr(0), '%00')} {problem}; "
        "give ?file= a file in an existing directory (spy:// writes the traffic it sees "
        "there), or leave it out (standard error)"
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
    if url_scheme(url) == "rfc2217" and RFC2217_UNANSWERED in str(exc):
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
    scheme = url_scheme(url)
    if scheme == "rfc2217":
        return lambda: Rfc2217Port(url, timeout=read_timeout_s, exclusive=True)
    timeout = 0 if scheme == "socket" else read_timeout_s
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
