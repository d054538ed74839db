"""Upload size limit: 413 from Content-Length up front, and while a chunked body streams."""

from __future__ import annotations

import select
import socket
from collections.abc import Callable, Iterator
from pathlib import Path

import httpx

from service.main import create_app
from tests.service.conftest import FULL_KEY, make_settings, read_response, serve

Client = Callable[[str], httpx.Client]
LIMIT = 2_000_000  # the test settings' max_upload_bytes


def test_declared_length_over_the_limit(client: Client) -> None:
    reply = client().post(
        "/v1/reconstructions",
        content=bytes(LIMIT + 1),
        headers={"Content-Type": "application/octet-stream"},
    )
    assert reply.status_code == 413
    assert reply.json()["code"] == "image_too_large"


def test_streamed_body_is_cut_off_at_the_limit(client: Client) -> None:
    sent = 0

    def chunks() -> Iterator[bytes]:
        nonlocal sent
        for _ in range(40):
            sent += 100_000
            yield bytes(100_000)

    reply = client().post(
        "/v1/reconstructions",
        content=chunks(),
        headers={"Content-Type": "application/octet-stream"},
    )
    assert reply.status_code == 413
    assert reply.json()["code"] == "image_too_large"


def test_streamed_multipart_over_the_limit(client: Client) -> None:
    def chunks() -> Iterator[bytes]:
        boundary = b"--b\r\n"
        yield boundary + b'Content-Disposition: form-data; name="file"; filename="f.npy"\r\n\r\n'
        for _ in range(30):
            yield bytes(100_000)
        yield b"\r\n--b--\r\n"

    reply = client().post(
        "/v1/reconstructions",
        content=chunks(),
        headers={"Content-Type": "multipart/form-data; boundary=b"},
    )
    assert reply.status_code == 413


def test_a_json_body_has_a_small_limit_even_without_a_key(client: Client) -> None:
    """FastAPI parses a JSON body before the key is checked: a 22 MB body from no key
    at all cost the API 650 MB. Commands and forms are a few hundred bytes."""
    big = b'{"command": "start", "pad": "' + b"x" * 100_000 + b'"}'
    for http in (client(""), client()):
        for path in ("/v1/devices/nosuch/control", "/v1/devices/nosuch/recordings"):
            reply = http.post(path, content=big, headers={"Content-Type": "application/json"})
            assert reply.status_code == 413, (path, reply.text)
            assert reply.json()["code"] == "body_too_large" and "MCAM_MAX_JSON_BYTES" in reply.text
    form = client().post("/v1/devices/nosuch/recordings", content=b"a=" + b"x" * 100_000,
                         headers={"Content-Type": "application/x-www-form-urlencoded"})
    assert form.status_code == 413 and form.json()["code"] == "body_too_large"
    small = client().post("/v1/devices/nosuch/control", json={"command": "start"})
    assert small.status_code == 404  # within the limit: on to the route (no such device)


def test_a_second_content_type_does_not_lift_the_json_limit(client: Client) -> None:
    """The body is parsed as the first Content-Type says; the limit followed the last,
    so JSON sent with a second, upload type went past the JSON limit to the parser."""
    big = b'{"command": "start", "pad": "' + b"x" * 100_000 + b'"}'
    headers = [("Content-Type", "application/json"), ("Content-Type", "application/octet-stream")]
    reply = client("").post("/v1/devices/nosuch/control", content=big, headers=headers)
    assert reply.status_code == 413 and reply.json()["code"] == "body_too_large"


def upload_socket(url: str, framing: bytes) -> socket.socket:
    """A connection to the API at ``url`` that sent an upload's head, with ``framing``
    (its Content-Length or Transfer-Encoding line), and none of its body."""
    host, port = url.removeprefix("http://").split(":")
    sock = socket.create_connection((host, int(port)), timeout=10)
    sock.sendall(b"POST /v1/reconstructions HTTP/1.1\r\nHost: x\r\n"
                 b"Authorization: Bearer " + FULL_KEY.encode() + b"\r\n"
                 b"Content-Type: application/octet-stream\r\n" + framing + b"\r\n\r\n")
    return sock


def read_to_end(sock: socket.socket) -> bytes:
    """Everything the server sends on ``sock`` until it closes the connection (a reset
    raises ``ConnectionResetError``)."""
    data = b""
    while chunk := sock.recv(65536):
        data += chunk
    return data


def test_a_refused_upload_is_read_so_its_client_gets_the_413(api: str) -> None:
    """The 413 for a declared length over the limit closed the connection with the body
    unread: the kernel reset it, and a client sending its whole upload before reading
    (httpx) often got "peer closed connection" instead of the 413. The body is now read
    and dropped first; the connection then closes cleanly."""
    body = bytes(LIMIT + 1_000_000)
    with upload_socket(api, b"Content-Length: %d" % len(body)) as sock:
        sock.sendall(body)
        reply = read_to_end(sock)
    assert reply.startswith(b"HTTP/1.1 413"), reply
    head, _, json_body = reply.partition(b"\r\n\r\n")
    assert b"image_too_large" in json_body and b"connection: close" in head.lower()


def test_a_refused_upload_that_expects_100_continue_is_answered_at_once(api: str) -> None:
    """A client asking ``Expect: 100-continue`` (curl, for large files) sends no body
    after a final answer: the 413 is not held waiting for one."""
    framing = b"Content-Length: %d\r\nExpect: 100-continue" % (LIMIT + 1)
    with upload_socket(api, framing) as sock:
        reply = read_to_end(sock)
    assert reply.startswith(b"HTTP/1.1 413") and b"100 Continue" not in reply, reply


def closed_by_server(sock: socket.socket) -> bool:
    """Whether the server has closed ``sock`` (an end of file is there to read)."""
    return bool(select.select([sock], [], [], 0)[0]) and sock.recv(1) == b""


def test_a_chunked_upload_trickling_on_after_its_413_is_cut_off(
    tmp_path: Path, redis_url: str
) -> None:
    """A chunked body refused as it crossed the limit got its 413 on a connection kept
    open, and uvicorn read the rest with no bound: a byte every 0.2 s after the 413 held
    the connection for good. The rest is now read within the body deadline, and the
    connection closed."""
    settings = make_settings(tmp_path, redis_url, http_body_timeout_s=30,
                             http_body_deadline_s=1)
    with serve(create_app(settings)) as url:
        with upload_socket(url, b"Transfer-Encoding: chunked") as sock:
            chunk = bytes(100_000)
            for _ in range(LIMIT // len(chunk) + 1):
                sock.sendall(b"%x\r\n" % len(chunk) + chunk + b"\r\n")
            reply = read_response(sock)
            for _ in range(100):  # 20 s at most: still open then, it would be for good
                if select.select([sock], [], [], 0.2)[0]:
                    break
                sock.sendall(b"1\r\nA\r\n")
            closed = closed_by_server(sock)
    assert reply.startswith(b"HTTP/1.1 413") and b"image_too_large" in reply, reply
    assert b"connection: close" in reply.lower() and closed


def test_a_chunked_upload_over_the_limit_in_its_last_read_is_answered_and_closed(
    tmp_path: Path, redis_url: str
) -> None:
    """A chunked body whose last read crossed the limit gets its 413 and the connection
    closed at once: nothing is left to drop, and a read past a body's end would wait for
    the client to leave (a client reading to the end of the connection, for good)."""
    settings = make_settings(tmp_path, redis_url, max_upload_bytes=1000)
    with serve(create_app(settings)) as url:
        with upload_socket(url, b"Transfer-Encoding: chunked") as sock:
            sock.sendall(b"7d0\r\n" + bytes(2000) + b"\r\n0\r\n\r\n")
            reply = read_to_end(sock)
    assert reply.startswith(b"HTTP/1.1 413") and b"connection: close" in reply.lower(), reply


def test_a_body_that_stops_arriving_gets_408(tmp_path: Path, redis_url: str) -> None:
    """A client that sends half a body and waits held a connection and a task for ever."""
    settings = make_settings(tmp_path, redis_url, http_body_timeout_s=1)
    with serve(create_app(settings)) as url:
        with upload_socket(url, b"Content-Length: 1000") as sock:
            sock.sendall(bytes(10))
            reply = read_response(sock).decode()
        assert reply.startswith("HTTP/1.1 408"), reply
        assert "request_timeout" in reply and "MCAM_HTTP_BODY_TIMEOUT_S" in reply
        assert httpx.get(f"{url}/health/live", timeout=5).status_code == 200


def test_a_body_trickling_in_past_the_deadline_gets_408(tmp_path: Path, redis_url: str) -> None:
    """A chunked upload sending a byte at a time, never pausing as long as the body
    timeout, stayed open for good: 260 such sockets held 123 of the server's connections."""
    settings = make_settings(tmp_path, redis_url, http_body_timeout_s=30,
                             http_body_deadline_s=1)
    with serve(create_app(settings)) as url:
        with upload_socket(url, b"Transfer-Encoding: chunked") as sock:
            for _ in range(100):  # 20 s at most: the body ends then, if nothing came back
                if select.select([sock], [], [], 0.2)[0]:
                    break
                sock.sendall(b"1\r\nA\r\n")
            else:
                sock.sendall(b"0\r\n\r\n")
            reply = read_response(sock).decode()
        assert reply.startswith("HTTP/1.1 408"), reply
        assert "request_timeout" in reply and "MCAM_HTTP_BODY_DEADLINE_S" in reply
        assert httpx.get(f"{url}/health/live", timeout=5).status_code == 200
