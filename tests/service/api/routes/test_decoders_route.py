"""/v1/decoders lists the registry with figures and marks the default."""

from __future__ import annotations

from collections.abc import Callable

import httpx

from models.decoders.registry import available_decoders
from tests.service.conftest import READ_KEY, SUBMIT_KEY

Client = Callable[[str], httpx.Client]


def test_lists_every_registered_decoder(client: Client) -> None:
    reply = client(READ_KEY).get("/v1/decoders")
    assert reply.status_code == 200
    listed = reply.json()
    assert [d["name"] for d in listed] == [spec.name for spec in available_decoders()]
    assert [d["name"] for d in listed if d["default"]] == ["itoh"]
    assert all(isinstance(d["figures"], dict) and d["description"] for d in listed)


def test_needs_the_read_scope(client: Client) -> None:
    assert client(SUBMIT_KEY).get("/v1/decoders").status_code == 403
