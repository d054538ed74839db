"""service/api/request_target.py: a request target in absolute form is routed by its path."""

from __future__ import annotations

import json
import socket

import pytest
from prometheus_client.parser import text_string_to_metric_families

from tests.service.conftest import FULL_KEY, read_response


def raw_get(api: str, target: str) -> tuple[str, bytes]:
    """``GET target`` sent as is to the API at ``api``: the status line and the body."""
    host, port = api.removeprefix("http://").split(":")
    with socket.create_connection((host, int(port)), timeout=30) as sock:
        sock.sendall(f"GET {target} HTTP/1.1\r\nHost: elsewhere\r\n"
                     f"Authorization: Bearer {FULL_KEY}\r\n\r\n".encode())
        head, _, body = read_response(sock).partition(b"\r\n\r\n")
    return head.split(b"\r\n")[0].decode(), body


@pytest.mark.parametrize("target", ["http://x/v1/decoders", "HTTPS://user@x:8/v1/decoders?a=1"])
def test_an_absolute_form_target_is_the_route_its_path_names(api: str, target: str) -> None:
    """RFC 9112 3.2.2: a server must accept it; it was 404 "Not Found", labelled
    ``unmatched`` in the metrics."""
    status, body = raw_get(api, target)
    assert status == "HTTP/1.1 200 OK", body
    assert any(decoder["name"] == "itoh" for decoder in json.loads(body))
    _, metrics = raw_get(api, "http://x/metrics")
    routes = {sample.labels["route"] for family in text_string_to_metric_families(
        metrics.decode()) for sample in family.samples
        if sample.name == "mcam_http_request_duration_seconds_count"}
    assert "/v1/decoders" in routes and "unmatched" not in routes


@pytest.mark.parametrize("target", ["v1/decoders", "*", "ftp://x/v1/decoders", "http://[/x"])
def test_a_target_that_is_neither_a_path_nor_a_url_is_400(api: str, target: str) -> None:
    status, body = raw_get(api, target)
    assert status.startswith("HTTP/1.1 400"), body
    error = json.loads(body)
    assert error["code"] == "bad_request" and "path starting with /" in error["message"]
