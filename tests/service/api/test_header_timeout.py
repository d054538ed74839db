"""The deadline on each request's line and headers (``service/api/header_timeout.py``),
under uvicorn with ``mcam api``'s options, on real sockets."""

from __future__ import annotations

import json
import socket
import time

import pytest

from service.api.header_timeout import timeout_response
from service.core.config import Settings
from tests.service.conftest import GET, listening, nothing_to_read, read_response, status_of


def test_a_request_head_that_never_finishes_gets_408_and_is_closed() -> None:
    """A slow-headers client held its connection for as long as it liked."""
    with listening(Settings(http_header_timeout_s=1)) as port:
        with socket.create_connection(("127.0.0.1", port), timeout=10) as sock:
            sock.sendall(b"GET / HTTP/1.1\r\nHost: x\r\nX-Slow: ")
            assert nothing_to_read(sock)  # the server waits for the rest of the head
            assert int(read_response(sock).split(b" ", 2)[1]) == 408
            assert sock.recv(1) == b""


def test_the_408_carries_the_headers_every_response_has() -> None:
    """It had only content-type, content-length and connection: no nosniff."""
    head = timeout_response(1.0).split(b"\r\n\r\n", 1)[0].decode().lower()
    assert "x-content-type-options: nosniff" in head.splitlines()


def test_a_connection_that_sends_nothing_is_closed_after_the_header_timeout() -> None:
    with listening(Settings(http_header_timeout_s=1)) as port:
        with socket.create_connection(("127.0.0.1", port), timeout=10) as sock:
            assert nothing_to_read(sock)  # not closed at once
            assert sock.recv(1) == b""


def test_the_header_timeout_applies_to_each_request_of_a_keep_alive_connection() -> None:
    """The deadline is per request head: one armed at the connection's start must not cut
    off a later request, and a later request's unfinished head gets its own 408."""
    with listening(Settings(http_header_timeout_s=1, http_keep_alive_s=5)) as port:
        status, sock = status_of(port, GET)
        with sock:
            assert status == 200
            time.sleep(1.2)  # past the first deadline, within keep-alive
            sock.sendall(GET)
            assert int(read_response(sock).split(b" ", 2)[1]) == 200
            sock.sendall(b"GET / HTTP/1.1\r\nHo")
            assert int(read_response(sock).split(b" ", 2)[1]) == 408
            assert sock.recv(1) == b""


def test_the_header_timeout_covers_a_request_after_a_body_the_app_did_not_read() -> None:
    """The app answered before reading the body; the body's last bytes then end that
    request and start the next, with uvicorn's keep-alive timer cancelled: the next
    request's unfinished head still gets its 408."""
    with listening(Settings(http_header_timeout_s=1, http_keep_alive_s=5)) as port:
        head = b"POST / HTTP/1.1\r\nHost: x\r\nContent-Length: 10\r\n\r\n"
        status, sock = status_of(port, head)
        with sock:
            assert status == 200
            sock.sendall(b"0123456789GET / HT")
            assert int(read_response(sock).split(b" ", 2)[1]) == 408
            assert sock.recv(1) == b""



@pytest.mark.parametrize(
    "request_head",
    [
        "GET /?x=\u0661 HTTP/1.1\r\nHost: x\r\n\r\n".encode(),  # a raw non-ASCII digit
        b"GET /a b HTTP/1.1\r\nHost: x\r\n\r\n",
        b"GET / HTTP/1.1\r\nHost: x\r\nNoColon\r\n\r\n",
    ],
)
def test_a_head_that_is_not_http_gets_a_json_400_saying_what_to_fix(request_head: bytes) -> None:
    """It got uvicorn's plain-text 'Invalid HTTP request received.', naming neither the
    fault nor the fix, without nosniff."""
    with listening(Settings()) as port:
        with socket.create_connection(("127.0.0.1", port), timeout=10) as sock:
            sock.sendall(request_head)
            head, _, body = read_response(sock).partition(b"\r\n\r\n")
            assert sock.recv(1) == b""  # closed
    lines = head.decode().lower().splitlines()
    assert lines[0] == "http/1.1 400 bad request"
    assert "content-type: application/json" in lines
    assert "x-content-type-options: nosniff" in lines
    error = json.loads(body)
    assert error["code"] == "bad_request"
    assert "percent-encode spaces and non-ASCII characters in the URL" in error["message"]
