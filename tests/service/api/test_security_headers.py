"""Security headers on the live API: nosniff everywhere, the viewer's CSP on its files only."""

from __future__ import annotations

from collections.abc import Callable

import httpx
import pytest

from service.api.security_headers import VIEWER_CSP

Client = Callable[[str], httpx.Client]


@pytest.mark.parametrize("path", ["/", "/index.html", "/app.js", "/style.css"])
def test_the_viewer_gets_a_csp_no_framing_nosniff_and_no_referrer(client: Client,
                                                                   path: str) -> None:
    for method in ("GET", "HEAD"):
        reply = client("").request(method, path)
        assert reply.headers["content-security-policy"] == VIEWER_CSP
        assert "frame-ancestors 'none'" in VIEWER_CSP and "script-src 'self'" in VIEWER_CSP
        assert reply.headers["x-frame-options"] == "DENY"
        assert reply.headers["x-content-type-options"] == "nosniff"
        assert reply.headers["referrer-policy"] == "no-referrer"


def test_api_replies_and_errors_are_nosniff_without_the_viewer_policy(client: Client) -> None:
    for key, path, status in (("", "/health/live", 200), ("", "/v1/jobs/x", 401),
                              ("full-key-0123456789abcdef", "/v1/decoders", 200),
                              ("", "/missing.txt", 404)):
        reply = client(key).get(path)
        assert reply.status_code == status, path
        assert reply.headers.get_list("x-content-type-options") == ["nosniff"], path
        assert "content-security-policy" not in reply.headers, path
    docs = client("").get("/docs")  # its own policy (tests/service/api/routes/test_docs_route)
    assert docs.headers["content-security-policy"] != VIEWER_CSP
