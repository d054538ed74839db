"""A full Redis (at its maxmemory, noeviction) through the real API: 503 store_full for
writes, reads go on, nothing accepted is lost, and work resumes once there is room."""

from __future__ import annotations

from collections.abc import Callable, Iterator

import httpx
import pytest
import redis

from service.core.config import Settings
from service.main import create_app
from tests.service.api.routes.test_metrics import samples
from tests.service.conftest import (
    FULL_KEY,
    PARAMS,
    finished_job,
    frame_png,
    running_worker,
    serve,
)
from worker.embedded_redis import connect
from worker.queue import JobQueue

Client = Callable[[str], httpx.Client]


@pytest.fixture
def server(settings: Settings) -> Iterator[redis.Redis]:
    """A direct connection to the API's Redis, for the operator's CONFIG SET."""
    assert settings.redis_url is not None
    conn = connect(settings.redis_url)
    yield conn
    conn.close()


def test_a_full_redis_refuses_submits_with_503_and_keeps_accepted_jobs(
    client: Client, server: redis.Redis, settings: Settings
) -> None:
    http = client()
    data, _ = frame_png()
    accepted = http.post("/v1/reconstructions", files={"file": ("f.png", data)})
    assert accepted.status_code == 202
    server.config_set("maxmemory", 1)  # anything held is more: every growing write refused

    refused = http.post("/v1/reconstructions", files={"file": ("f.png", data)})
    assert refused.status_code == 503, refused.text
    body = refused.json()
    assert body["code"] == "store_full"
    assert "nothing from this request was stored" in body["message"]
    assert refused.headers["Retry-After"].isdigit()
    job = http.get(f"/v1/jobs/{accepted.json()['id']}")  # reads go on
    assert job.status_code == 200 and job.json()["state"] == "queued"
    metrics = samples(http.get("/metrics").text)
    assert metrics[("mcam_redis_maxmemory_bytes", ())] == 1.0
    assert metrics[("mcam_redis_used_memory_bytes", ())] > 1.0

    server.config_set("maxmemory", 0)
    with running_worker(settings):
        assert finished_job(http, accepted.json()["id"])["state"] == "succeeded"
    again = http.post("/v1/reconstructions", files={"file": ("f.png", data)})
    assert again.status_code == 202


def test_an_api_started_on_a_full_redis_serves_reads(
    settings: Settings, server: redis.Redis
) -> None:
    """Opening the job queue writes (its consumer group) and a full Redis refuses that
    even when the group exists: reads answered 503 store_full in such a process."""
    queue = JobQueue(server, maxlen=10, max_deliveries=3, claim_idle_ms=1000)
    _, codes = frame_png()
    job = queue.submit("reconstruction", codes, PARAMS, "itoh")
    server.config_set("maxmemory", 1)
    with serve(create_app(settings)) as url, httpx.Client(
        base_url=url, headers={"Authorization": f"Bearer {FULL_KEY}"}
    ) as http:
        reply = http.get(f"/v1/jobs/{job.id}")
        assert reply.status_code == 200 and reply.json()["state"] == "queued"
        data, _ = frame_png()
        refused = http.post("/v1/reconstructions", files={"file": ("f.png", data)})
        assert refused.status_code == 503 and refused.json()["code"] == "store_full"
    server.config_set("maxmemory", 0)
