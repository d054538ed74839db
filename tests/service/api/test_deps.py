"""Authentication and rate limiting over real HTTP (two API processes share the limit)."""

from __future__ import annotations

import logging
from pathlib import Path

import httpx
import pytest

from service.main import create_app
from tests.service.conftest import FULL_KEY, READ_KEY, SUBMIT_KEY, make_settings, serve
from worker.embedded_redis import EmbeddedRedis


def test_missing_wrong_and_malformed_keys_are_401(api: str) -> None:
    for headers in ({}, {"Authorization": "Bearer nope"}, {"Authorization": f"Basic {FULL_KEY}"}):
        reply = httpx.get(f"{api}/v1/decoders", headers=headers)
        assert reply.status_code == 401
        assert reply.json()["code"] == "unauthorized"
        assert reply.headers["WWW-Authenticate"] == "Bearer"


@pytest.mark.parametrize(
    "value", [FULL_KEY, f"Basic {FULL_KEY}", f"Token {FULL_KEY}", "Bearer"]
)
def test_a_key_sent_without_bearer_is_told_so_not_that_it_is_missing(
    api: str, value: str
) -> None:
    """``Authorization: <key>`` (or another scheme, or Bearer with no key) was answered
    "missing API key", though the header had come; the key itself is not echoed."""
    reply = httpx.get(f"{api}/v1/decoders", headers={"Authorization": value})
    assert reply.status_code == 401
    message = reply.json()["message"]
    assert message.startswith("the Authorization header is not 'Bearer <key>'"), message
    assert FULL_KEY not in message
    assert reply.headers["WWW-Authenticate"] == "Bearer"


@pytest.mark.parametrize(
    ("key", "path", "scope"),
    [(READ_KEY, "/v1/jobs/" + "0" * 32, "submit"), (SUBMIT_KEY, "/v1/decoders", "read")],
)
def test_a_key_without_the_scope_is_told_which_keys_have_it(
    api: str, key: str, path: str, scope: str
) -> None:
    """The 403 said the key lacked the scope, not where a key gets it."""
    method = "DELETE" if scope == "submit" else "GET"
    reply = httpx.request(method, f"{api}{path}", headers={"Authorization": f"Bearer {key}"})
    assert reply.status_code == 403
    message = reply.json()["message"]
    assert f"lacks the {scope!r} scope needed here" in message
    assert f"KEY:{scope}" in message and "MCAM_API_KEYS" in message


def test_rate_limit_is_shared_by_api_processes(tmp_path: Path, redis_url: str) -> None:
    settings = make_settings(tmp_path, redis_url, rate_limit_per_minute=4)
    headers = {"Authorization": f"Bearer {FULL_KEY}"}
    with serve(create_app(settings)) as first, serve(create_app(settings)) as second:
        codes = [
            httpx.get(f"{url}/v1/decoders", headers=headers).status_code
            for url in (first, second, first, second)
        ]
        assert codes == [200, 200, 200, 200]
        limited = httpx.get(f"{second}/v1/decoders", headers=headers)
        assert limited.status_code == 429
        assert limited.json()["code"] == "rate_limited"
        assert 1 <= int(limited.headers["Retry-After"]) <= 60
        assert httpx.get(f"{first}/health/live").status_code == 200  # ops endpoints: no key


def test_generated_key_works(tmp_path: Path, redis_url: str) -> None:
    settings = make_settings(tmp_path, redis_url, api_keys=None)
    with serve(create_app(settings)) as url:
        key = (settings.data_dir / "api_keys").read_text().strip()
        reply = httpx.get(f"{url}/v1/decoders", headers={"Authorization": f"Bearer {key}"})
        assert reply.status_code == 200


def test_a_redis_outage_warns_once_not_once_a_request(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """With Redis down every request's rate-limit check failed and logged a warning."""
    embedded = EmbeddedRedis(tmp_path / "r")
    settings = make_settings(tmp_path, embedded.start())
    headers = {"Authorization": f"Bearer {FULL_KEY}"}
    with serve(create_app(settings)) as url:
        embedded.stop()
        with caplog.at_level(logging.WARNING, logger="service.api.deps"):
            replies = [httpx.get(f"{url}/v1/decoders", headers=headers) for _ in range(20)]
    assert {reply.status_code for reply in replies} == {200}  # needs no Redis: served
    warnings = [r for r in caplog.records if r.name == "service.api.deps"]
    assert len(warnings) == 1 and "not enforced" in warnings[0].getMessage()
