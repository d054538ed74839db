"""service/api/errors.py: every client mistake is a JSON error naming what to fix."""

from __future__ import annotations

from collections.abc import Callable

import httpx

from tests.service.conftest import FULL_KEY

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


def test_field_errors_name_the_field(client: Client) -> None:
    reply = client(FULL_KEY).post(
        "/v1/devices/cam1/control", json={"command": "set_frame_rate", "fps": -1}
    )
    assert reply.status_code == 422
    assert reply.json()["details"][0]["field"] == "set_frame_rate.fps"
