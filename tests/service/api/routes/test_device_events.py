"""``/v1/devices/{id}/events``: the cap on open streams, a stream that loses Redis, and
event ids Redis would refuse."""

from __future__ import annotations

import os
import signal
import time
from collections.abc import Callable
from pathlib import Path

import httpx

from service.core.config import Settings
from service.main import create_app
from tests.device.conftest import wait_for
from tests.service.api.conftest import stopped_device
from tests.service.conftest import READ_KEY, make_settings, serve
from worker.embedded_redis import EmbeddedRedis, connect
from worker.redis_keys import DEVICES_SET, events_stream


def test_event_streams_are_capped_and_a_closed_one_frees_its_slot(
    tmp_path: Path, redis_url: str
) -> None:
    """Each stream holds a Redis connection blocked on XREAD: 200 from one key took 213
    connections and nothing ended them. Past MCAM_MAX_EVENT_STREAMS a new one is 503."""
    settings = make_settings(tmp_path, redis_url, max_event_streams=2)
    connect(redis_url).sadd(DEVICES_SET, "cam1")
    connect(redis_url).xadd(events_stream("cam1"), {"type": "frame"})  # one for limit=1
    headers = {"Authorization": f"Bearer {READ_KEY}"}
    with serve(create_app(settings)) as url, httpx.Client(base_url=url, headers=headers) as http:
        opened = [http.stream("GET", "/v1/devices/cam1/events") for _ in range(2)]
        for stream in opened:
            assert stream.__enter__().status_code == 200
        refused = http.get("/v1/devices/cam1/events")
        assert refused.status_code == 503 and refused.json()["code"] == "too_many_streams"
        assert "MCAM_MAX_EVENT_STREAMS" in refused.text and refused.headers["retry-after"]
        opened[0].__exit__(None, None, None)
        one = {"since": "0", "limit": 1}
        assert wait_for(lambda: http.get("/v1/devices/cam1/events", params=one).status_code
                        == 200, 10)
        opened[1].__exit__(None, None, None)


def test_an_event_stream_that_loses_redis_ends_with_an_error_event(tmp_path: Path) -> None:
    """Redis killed under an open stream: it ends with an ``error`` event and a retry
    time (the client resumes from its last id), not a connection cut after a traceback."""
    embedded = EmbeddedRedis(tmp_path / "redis-home")
    with embedded as redis_url, serve(create_app(make_settings(tmp_path, redis_url))) as url:
        connect(redis_url).sadd(DEVICES_SET, "cam1")
        headers = {"Authorization": f"Bearer {READ_KEY}"}
        with httpx.Client(base_url=url, headers=headers, timeout=30) as http, http.stream(
            "GET", "/v1/devices/cam1/events"
        ) as stream:
            assert stream.status_code == 200
            lines = stream.iter_lines()
            assert next(lines) == "retry: 2000"
            pid = embedded.pid
            assert pid is not None
            os.kill(pid, signal.SIGKILL)
            rest = list(lines)
        assert "event: error" in rest and "retry: 5000" in rest
        assert any('"code": "queue_unavailable"' in line for line in rest)


def test_an_event_id_in_other_scripts_digits_is_refused(
    client: Callable[..., httpx.Client], settings: Settings
) -> None:
    """Arabic-Indic digits pass \\d and int(), then Redis refuses the id inside the
    started stream: a 200, a broken stream and a traceback, repeated by every retry."""
    assert settings.redis_url is not None
    connect(settings.redis_url).sadd(DEVICES_SET, "cam1")
    http = client(READ_KEY)
    reply = http.get("/v1/devices/cam1/events", params={"since": "\u0661-\u0660"})
    assert reply.status_code == 422, reply.text


def test_a_malformed_event_id_says_what_an_event_id_is_not_a_regex(
    client: Callable[..., httpx.Client], settings: Settings
) -> None:
    """``since=abc`` (or a Last-Event-ID of ``abc``) was refused with "String should match
    pattern '^(\\$|0|[0-9]+-[0-9]+)$'": a regex, not what to send. The refusal now names
    the event id's form and the other values ``since`` takes."""
    assert settings.redis_url is not None
    connect(settings.redis_url).sadd(DEVICES_SET, "cam1")
    http = client(READ_KEY)
    for params, headers in [({"since": "abc"}, {}), ({}, {"Last-Event-ID": "abc"})]:
        reply = http.get("/v1/devices/cam1/events", params=params, headers=headers)
        assert reply.status_code == 422, reply.text
        message = reply.json()["message"]
        assert "pattern" not in message and "'abc' is not an event id" in message
        assert "'<ms>-<seq>', as the stream's id: lines send it" in message
    since = http.get("/v1/devices/cam1/events", params={"since": "-1"}).json()["message"]
    assert "$ for new events only, 0 for every kept event" in since


def test_an_event_stream_of_a_forgotten_device_ends(
    client: Callable[..., httpx.Client], settings: Settings
) -> None:
    """A device forgotten (DELETE /v1/devices/{id}) under an open stream: it ends with an
    ``error`` event saying so. Before, it sent keep-alives for ever, holding one of the
    MCAM_MAX_EVENT_STREAMS slots and a Redis connection for a device that no longer
    exists (a dashboard of a retired camera never learned it was gone)."""
    assert settings.redis_url is not None
    stopped_device(settings, "cam1")
    with client(READ_KEY).stream("GET", "/v1/devices/cam1/events") as stream:
        assert stream.status_code == 200
        lines = stream.iter_lines()
        assert next(lines) == "retry: 2000"
        assert client().delete("/v1/devices/cam1").status_code == 200
        deadline = time.monotonic() + 30
        rest = []
        for line in lines:  # keep-alives, then the end
            rest.append(line)
            if line == "event: error" or time.monotonic() > deadline:
                rest += [next(lines)]
                break
    assert "event: error" in rest, "the stream went on with keep-alives"
    assert any('"code": "not_found"' in line and "forgotten" in line for line in rest)
