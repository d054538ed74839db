"""A deadline for each HTTP request's line and headers, which uvicorn (0.54, h11) lacks.

uvicorn times out an idle keep-alive connection, but not a fresh connection that sends
nothing, nor one whose request line and headers never finish (a slow-headers client,
"slowloris"): each holds a slot of ``MCAM_HTTP_MAX_CONNECTIONS`` until the client goes.
:func:`header_timeout_protocol` makes uvicorn's h11 protocol with a deadline of
``timeout_s`` seconds, armed when a connection opens and when the first bytes of a
later request on it arrive (or the bytes that end a request leave the connection idle
with no timer), and disarmed once h11 has the whole head. At the deadline
a connection that sent part of a request gets ``408`` (with a JSON body naming the
limit) and is closed; one that sent nothing is closed. Request bodies have their own
timeout (``MCAM_HTTP_BODY_TIMEOUT_S``, :mod:`service.api.body_timeout`).

A request head h11 cannot parse (a space or a raw non-ASCII character in the URL, a
header line without a colon, a head past ``MCAM_HTTP_MAX_HEADER_BYTES``) got uvicorn's
plain-text 400 "Invalid HTTP request received.", which named neither the fault nor
the fix and lacked the headers every response has; the protocol answers it with the
API's JSON error (:func:`malformed_response`) instead.
"""

from __future__ import annotations

import asyncio
import json
import logging

import h11
from uvicorn.protocols.http.h11_impl import H11Protocol

from service.api.errors import error_body
from service.api.security_headers import API_HEADERS

log = logging.getLogger(__name__)


def raw_error(status: str, code: str, message: str) -> bytes:
    """A raw JSON error response (``status``: e.g. ``408 Request Timeout``) that closes
    the connection, with the headers every response has."""
    body = json.dumps(error_body(code, message)).encode()
    extra = "".join(f"{name}: {value}\r\n" for name, value in API_HEADERS.items())
    head = (
        f"HTTP/1.1 {status}\r\ncontent-type: application/json\r\n"
        f"{extra}content-length: {len(body)}\r\nconnection: close\r\n\r\n"
    )
    return head.encode() + body


def timeout_response(timeout_s: float) -> bytes:
    """The raw ``408`` sent to a client whose request head did not arrive in time, with
    the headers every response has (``nosniff``: it had none)."""
    return raw_error(
        "408 Request Timeout", "request_timeout",
        f"the request line and headers did not arrive within {timeout_s:g} s "
        "(MCAM_HTTP_HEADER_TIMEOUT_S); send the whole head at once",
    )  # fmt: skip


def malformed_response() -> bytes:
    """The raw ``400`` sent to a client whose request head is not HTTP/1.1 that h11 can
    parse, saying what usually makes it so."""
    return raw_error(
        "400 Bad Request", "bad_request",
        "the request line or headers could not be parsed as HTTP/1.1: percent-encode "
        "spaces and non-ASCII characters in the URL (%20, %C3%A9), send each header as "
        "'Name: value' in ASCII, and keep the request line and headers within "
        "MCAM_HTTP_MAX_HEADER_BYTES",
    )  # fmt: skip


class HeaderDeadlineProtocol(H11Protocol):
    """uvicorn's h11 protocol with a deadline on each request head (see the module)."""

    #: Seconds a request's line and headers may take (set by :func:`header_timeout_protocol`).
    header_timeout_s: float = 10.0
    _deadline: asyncio.TimerHandle | None = None

    def connection_made(self, transport: asyncio.Transport) -> None:  # type: ignore[override]
        super().connection_made(transport)
        self._arm()

    def data_received(self, data: bytes) -> None:
        if self._deadline is None and self.conn.their_state is h11.IDLE:
            self._arm()
        super().data_received(data)
        if self.conn.their_state is not h11.IDLE:
            self._disarm()
        elif self._deadline is None:
            # A request ended within these bytes (the rest of a body the app answered
            # before reading): uvicorn cancelled its keep-alive timer on them and armed
            # nothing, and what follows is the next request's head, if any.
            self._arm()

    def send_400_response(self, msg: str) -> None:
        """Answer a head h11 could not parse with :func:`malformed_response` (uvicorn's
        ``msg`` is always "Invalid HTTP request received.") and close the connection."""
        self._disarm()
        self.transport.write(malformed_response())
        self.transport.close()

    def connection_lost(self, exc: Exception | None) -> None:
        self._disarm()
        super().connection_lost(exc)

    def _arm(self) -> None:
        self._deadline = self.loop.call_later(self.header_timeout_s, self._expire)

    def _disarm(self) -> None:
        if self._deadline is not None:
            self._deadline.cancel()
            self._deadline = None

    def _expire(self) -> None:
        self._deadline = None
        if self.transport.is_closing() or self.conn.their_state is not h11.IDLE:
            return
        if self.conn.trailing_data[0]:  # part of a head, buffered by h11
            log.info("request head from %s unfinished after %g s: 408", self.client,
                     self.header_timeout_s)  # fmt: skip
            self.transport.write(timeout_response(self.header_timeout_s))
        self.transport.close()


def header_timeout_protocol(timeout_s: float) -> type[HeaderDeadlineProtocol]:
    """uvicorn's h11 protocol class (its ``http`` option) with a ``timeout_s`` deadline
    on each request's line and headers."""
    if timeout_s <= 0:
        raise ValueError(f"the header timeout must be > 0 s, got {timeout_s}")
    settings = {"header_timeout_s": timeout_s}
    return type("HeaderDeadlineProtocol", (HeaderDeadlineProtocol,), settings)
