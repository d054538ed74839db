"""Security headers on the live API: nosniff everywhere, the viewer's CSP on its files only."""

from __future__ import annotations

from collections.abc import Callable

import httpx
import pytest

Client = Callable[[str], httpx.Client]

#: The viewer's policy as the README states it: only its own scripts, styles and origin;
#: images also from ``blob:`` and ``data:``; no framing (written out here, not imported,
#: so that a change to the policy in the code has to be made here too).
README_VIEWER_POLICY = {
    "default-src": ["'self'"],
    "img-src": ["'self'", "blob:", "data:"],
    "script-src": ["'self'"],
    "style-src": ["'self'"],
    "connect-src": ["'self'"],
    "frame-ancestors": ["'none'"],
    "base-uri": ["'none'"],
    "form-action": ["'self'"],
    "object-src": ["'none'"],
}


def directives(policy: str) -> dict[str, list[str]]:
    """A Content Security Policy header as {directive: its sources, in order}."""
    parsed: dict[str, list[str]] = {}
    for directive in filter(None, (part.strip() for part in policy.split(";"))):
        name, *sources = directive.split()
        assert name not in parsed, f"{name} twice in {policy!r}"
        parsed[name] = sources
    return parsed


@pytest.mark.parametrize("path", ["/", "/index.html", "/app.js", "/style.css"])
def test_the_viewer_gets_a_csp_no_framing_nosniff_and_no_referrer(client: Client,
                                                                   path: str) -> None:
    for method in ("GET", "HEAD"):
        reply = client("").request(method, path)
        policy = directives(reply.headers["content-security-policy"])
        sources = [source for values in policy.values() for source in values]
        lax = [s for s in sources if s.startswith("'unsafe-") or "*" in s or "http" in s]
        assert not lax, f"the viewer's policy lets in inline code or other origins: {lax}"
        assert policy == README_VIEWER_POLICY
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
    docs = client("").get("/docs")  # its own policy (tests/service/api/routes/test_docs)
    assert directives(docs.headers["content-security-policy"]) != README_VIEWER_POLICY


@pytest.mark.parametrize("path", ["/", "/app.js", "/live.js", "/style.css"])
def test_the_viewer_s_files_are_revalidated_on_each_load(client: Client, path: str) -> None:
    """With Last-Modified and no Cache-Control a browser kept the files fresh for a tenth
    of their age (days for an installed checkout), and ran the old app.js against an
    upgraded server; each load now asks, and gets 304 while the file is unchanged."""
    first = client("").get(path)
    assert first.headers["cache-control"] == "no-cache"
    again = client("").get(path, headers={"If-None-Match": first.headers["etag"]})
    assert again.status_code == 304
    assert again.headers["cache-control"] == "no-cache"
