"""/metrics: Prometheus text with request, queue-wait, decode, encode histograms and queue state."""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path

import httpx
from prometheus_client.parser import text_string_to_metric_families

from service.core.config import Settings
from service.main import create_app
from tests.service.conftest import READ_KEY, SUBMIT_KEY, frame_png, make_settings, serve
from worker.deliveries import StreamConsumer
from worker.embedded_redis import connect
from worker.redis_keys import JOBS_STREAM
from worker.runner import Worker

Client = Callable[[str], httpx.Client]


def samples(text: str) -> dict[tuple[str, tuple[tuple[str, str], ...]], float]:
    return {
        (s.name, tuple(sorted(s.labels.items()))): s.value
        for family in text_string_to_metric_families(text)
        for s in family.samples
    }


def settled_metrics(http: httpx.Client, timeout_s: float = 30.0) -> httpx.Response:
    """/metrics once the worker has recorded its job: it marks the job succeeded (which
    answers the waiting POST) before it acknowledges the entry and observes the timings."""
    deadline = time.monotonic() + timeout_s
    while True:
        reply = http.get("/metrics")
        decoded = samples(reply.text).get(("mcam_decode_seconds_count", ()))
        if reply.status_code != 200 or decoded == 1.0 or time.monotonic() > deadline:
            return reply
        time.sleep(0.05)


def test_metrics_after_one_job(client: Client, worker: Worker) -> None:
    http = client()
    data, _ = frame_png()
    job = http.post(
        "/v1/reconstructions", files={"file": ("f.png", data)}, headers={"Prefer": "wait=30"}
    )
    assert job.status_code == 200
    reply = settled_metrics(http)
    assert reply.status_code == 200 and reply.headers["content-type"].startswith("text/plain")
    values = samples(reply.text)
    for name in (
        "mcam_decode_seconds_count",
        "mcam_encode_seconds_count",
        "mcam_queue_wait_seconds_count",
    ):
        assert values[(name, ())] == 1.0, name
    assert values[("mcam_jobs_processed_total", (("state", "succeeded"),))] == 1.0
    assert values[("mcam_jobs_active", (("state", "queued"),))] == 0.0
    assert values[("mcam_jobs_active", (("state", "running"),))] == 0.0
    assert values[("mcam_queue_depth", ())] == 0.0
    assert values[("mcam_dead_letter_stream_length", ())] == 0.0
    names = [family.name for family in text_string_to_metric_families(reply.text)]
    assert len(names) == len(set(names)), "two metric families share a name"
    assert values[("mcam_queue_up", ())] == 1.0
    posted = (
        "mcam_http_request_duration_seconds_count",
        (("method", "POST"), ("route", "/v1/reconstructions"), ("status", "200")),
    )
    assert values[posted] == 1.0


def test_made_up_methods_share_one_label(client: Client) -> None:
    """Any token is a valid HTTP method: each used to add a label value for good."""
    http = client()
    for n in range(5):
        http.request(f"FAKE{n}", "/health/live")
    values = samples(http.get("/metrics").text)
    methods = {dict(labels)["method"] for name, labels in values
               if name == "mcam_http_request_duration_seconds_count"}
    assert "other" in methods and not any(m.startswith("FAKE") for m in methods)


def test_a_refused_body_and_a_head_are_labelled_with_their_route(client: Client) -> None:
    """A 413 (refused before routing) was labelled 'unmatched' like a 404, and a HEAD as
    the GET it is answered with."""
    http = client()
    big = http.post("/v1/reconstructions", content=b"x" * 3_000_000,
                    headers={"Content-Type": "application/octet-stream"})
    assert big.status_code == 413
    assert http.head("/v1/decoders").status_code == 200
    values = samples(http.get("/metrics").text)
    count = "mcam_http_request_duration_seconds_count"
    assert values[(count, (("method", "POST"), ("route", "/v1/reconstructions"),
                           ("status", "413")))] == 1.0
    assert values[(count, (("method", "HEAD"), ("route", "/v1/decoders"),
                           ("status", "200")))] == 1.0


def test_queue_depth_counts_only_jobs_no_worker_took(client: Client, settings: Settings) -> None:
    """A running job was counted in both mcam_queue_depth ('waiting') and
    mcam_queue_pending."""
    http = client()
    data, _ = frame_png()
    for _ in range(2):
        assert http.post("/v1/reconstructions", files={"file": ("f.png", data)}).status_code == 202
    assert settings.redis_url is not None
    consumer = StreamConsumer(connect(settings.redis_url), JOBS_STREAM, "w-j0", max_deliveries=3)
    assert len(consumer.read_new(block_ms=None)) == 1
    values = samples(http.get("/metrics").text)
    assert values[("mcam_queue_depth", ())] == 1.0
    assert values[("mcam_queue_pending", ())] == 1.0


def test_metrics_need_a_read_key_unless_made_public(
    client: Client, tmp_path: Path, redis_url: str
) -> None:
    """They name every device and show the service's load: they were open to anyone."""
    assert client("").get("/metrics").status_code == 401
    assert client(SUBMIT_KEY).get("/metrics").status_code == 403
    assert client(READ_KEY).get("/metrics").status_code == 200
    public = make_settings(tmp_path, redis_url, metrics_public=True)
    with serve(create_app(public)) as url:
        assert httpx.get(f"{url}/metrics").status_code == 200
