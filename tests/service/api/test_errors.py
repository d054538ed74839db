"""service/api/errors.py: every client mistake is a JSON error naming what to fix."""

from __future__ import annotations

import logging
import socket
from collections.abc import Callable
from pathlib import Path

import httpx
import pytest
from prometheus_client.parser import text_string_to_metric_families

from service.core.config import Settings
from service.main import create_app
from tests.device.conftest import wait_for
from tests.service.conftest import FULL_KEY, frame_png, make_settings, serve

Client = Callable[[str], httpx.Client]


def test_a_body_that_is_not_json_is_named_as_such(client: Client) -> None:
    reply = client(FULL_KEY).post(
        "/v1/devices/cam1/control",
        content=b'{"command": "stop"',
        headers={"Content-Type": "application/json"},
    )
    assert reply.status_code == 422
    body = reply.json()
    assert body["code"] == "invalid_input"
    assert body["details"][0]["field"] == "body"
    assert "not valid JSON" in body["message"]
    assert "Content-Type: application/json" in body["message"]


@pytest.mark.parametrize(
    "headers", [{"Content-Type": "application/json"}, {}, {"Content-Type": "text/plain"}]
)
def test_a_json_route_without_a_body_says_so(client: Client, headers: dict[str, str]) -> None:
    """It said "invalid request: request: Field required"."""
    reply = client(FULL_KEY).post("/v1/devices/cam1/control", headers=headers)
    assert reply.status_code == 422
    body = reply.json()
    assert body["details"] == [{"field": "body", "message": "the request has no body; send a "
                                "JSON object with the header 'Content-Type: application/json'"}]
    assert "Field required" not in body["message"] and "was not read" not in body["message"]


def test_a_required_query_parameter_left_out_is_named_as_one(client: Client) -> None:
    """GET /v1/jobs without idempotency_key said "idempotency_key: Field required"."""
    reply = client(FULL_KEY).get("/v1/jobs")
    assert reply.status_code == 422
    body = reply.json()
    assert body["details"] == [{"field": "idempotency_key", "message": "this route needs the "
                                "query parameter idempotency_key (?idempotency_key=...; /docs "
                                "says what it is)"}]  # fmt: skip
    assert "Field required" not in body["message"]


def test_a_body_sent_as_another_type_than_json_is_not_called_missing(client: Client) -> None:
    reply = client(FULL_KEY).post("/v1/devices/cam1/control", content=b'{"command": "stop"}',
                                  headers={"Content-Type": "text/plain"})
    assert reply.status_code == 422
    assert "no body" not in reply.text and "'text/plain' and was not read" in reply.text


def test_field_errors_name_the_field(client: Client) -> None:
    reply = client(FULL_KEY).post(
        "/v1/devices/cam1/control", json={"command": "set_frame_rate", "fps": -1}
    )
    assert reply.status_code == 422
    assert reply.json()["details"][0]["field"] == "set_frame_rate.fps"


def test_a_bug_is_a_logged_json_500_and_the_connection_lives_on(
    settings: Settings, caplog: pytest.LogCaptureFixture
) -> None:
    app = create_app(settings)

    def broken() -> None:
        raise RuntimeError("a bug")

    app.add_api_route("/v1/broken", broken)
    app.router.routes.insert(0, app.router.routes.pop())  # ahead of the viewer's "/" mount
    with serve(app) as url, httpx.Client(base_url=url) as http:
        reply = http.get("/v1/broken")
        assert reply.status_code == 500
        assert reply.json() == {
            "code": "internal_error",
            "message": "an internal error occurred; it has been logged",
        }
        assert "a bug" not in reply.text
        assert http.get("/health/live").status_code == 200
    assert any("internal error on GET /v1/broken" in r.getMessage() for r in caplog.records)


def test_a_json_body_too_deep_to_parse_says_so(client: Client) -> None:
    deep = "[" * 30_000 + "]" * 30_000  # within MCAM_MAX_JSON_BYTES, past the recursion limit
    reply = client(FULL_KEY).post(
        "/v1/devices/cam1/control",
        content=deep.encode(),
        headers={"Content-Type": "application/json"},
    )
    assert reply.status_code == 400, reply.text
    assert reply.json()["code"] == "bad_request"
    assert "could not be parsed" in reply.json()["message"]


def test_a_json_integer_past_the_digit_limit_is_named_not_called_nesting(
    client: Client,
) -> None:
    """``{"command": "set_frame_rate", "fps": 1000...0}`` with 5000 digits (valid JSON, a
    flat object) was "could not be parsed (nested too deeply, or not JSON); send a flat
    JSON object": Python's integer digit limit refused the number. It is named now."""
    huge = b'{"command": "set_frame_rate", "fps": 1' + b"0" * 5000 + b"}"
    reply = client(FULL_KEY).post(
        "/v1/devices/cam1/control", content=huge, headers={"Content-Type": "application/json"}
    )
    assert reply.status_code == 400, reply.text
    message = reply.json()["message"]
    assert "nested" not in message
    assert "an integer in it has more than 4300 digits" in message


def test_a_body_that_is_not_sent_as_json_is_named(client: Client) -> None:
    reply = client(FULL_KEY).post(
        "/v1/devices/cam1/control",
        content=b'{"command": "stop"}',
        headers={"Content-Type": "text/plain"},
    )
    assert reply.status_code == 422, reply.text
    assert "'text/plain' and was not read" in reply.json()["message"]


def test_a_full_queue_says_when_to_retry(tmp_path: Path, redis_url: str) -> None:
    """503 queue_full said 'retry in a few seconds' with no Retry-After."""
    settings = make_settings(tmp_path, redis_url, jobs_maxlen=1)
    data, _ = frame_png()
    with serve(create_app(settings)) as url:
        replies = [
            httpx.post(f"{url}/v1/reconstructions", files={"file": ("f.png", data)},
                       headers={"Authorization": f"Bearer {FULL_KEY}"}, timeout=60)
            for _ in range(2)
        ]
    assert replies[0].status_code == 202
    assert replies[1].status_code == 503 and replies[1].json()["code"] == "queue_full"
    assert replies[1].headers["retry-after"] == "5"


CUT_BODIES = {
    "octet-stream": ("application/octet-stream", b"\x89PNG"),
    "multipart": ("multipart/form-data; boundary=XYZ",
                  b'--XYZ\r\nContent-Disposition: form-data; name="file"; filename="a.png"'
                  b"\r\n\r\n\x89PNG"),
    "json": ("application/json", b'{"comm'),
}


@pytest.mark.parametrize("kind", CUT_BODIES)
def test_a_client_that_leaves_mid_body_is_a_quiet_499(
    api: str, client: Client, kind: str, caplog: pytest.LogCaptureFixture
) -> None:
    """Headers promising 1000 bytes, a few sent, then the connection closed: the upload was
    logged as an internal error with a 50-line ClientDisconnect traceback and counted as
    a 500 (a JSON body as a 400 'could not be parsed')."""
    media, body = CUT_BODIES[kind]
    path, route = ("/v1/devices/cam1/control", "/v1/devices/{device_id}/control") \
        if kind == "json" else ("/v1/reconstructions", "/v1/reconstructions")
    host, port = api.removeprefix("http://").split(":")
    with socket.create_connection((host, int(port)), timeout=10) as sock:
        sock.sendall(f"POST {path} HTTP/1.1\r\nHost: x\r\nAuthorization: Bearer {FULL_KEY}"
                     f"\r\nContent-Type: {media}\r\nContent-Length: 1000\r\n\r\n".encode()
                     + body)
    http = client(FULL_KEY)

    def statuses() -> set[str]:
        return {labels["status"] for labels in request_labels(http.get("/metrics").text)
                if labels["route"] == route}

    assert wait_for(lambda: bool(statuses()), 30)
    assert statuses() == {"499"}
    assert not [r for r in caplog.records if r.levelno >= logging.WARNING], caplog.text
    assert http.get("/health/live").status_code == 200


def request_labels(metrics: str) -> list[dict[str, str]]:
    """The labels of each ``mcam_http_request_duration_seconds_count`` sample."""
    return [sample.labels for family in text_string_to_metric_families(metrics)
            for sample in family.samples
            if sample.name == "mcam_http_request_duration_seconds_count"]
