"""/metrics: Prometheus text with request, queue-wait, decode, encode histograms and queue state."""

from __future__ import annotations

from collections.abc import Callable

import httpx
from prometheus_client.parser import text_string_to_metric_families

from tests.service.conftest import frame_png
from worker.runner import Worker

Client = Callable[[str], httpx.Client]


def samples(text: str) -> dict[tuple[str, tuple[tuple[str, str], ...]], float]:
    return {
        (s.name, tuple(sorted(s.labels.items()))): s.value
        for family in text_string_to_metric_families(text)
        for s in family.samples
    }


def test_metrics_after_one_job(client: Client, worker: Worker) -> None:
    http = client()
    data, _ = frame_png()
    job = http.post(
        "/v1/reconstructions", files={"file": ("f.png", data)}, headers={"Prefer": "wait=30"}
    )
    assert job.status_code == 200
    reply = httpx.get(f"{str(http.base_url).rstrip('/')}/metrics")
    assert reply.status_code == 200 and reply.headers["content-type"].startswith("text/plain")
    values = samples(reply.text)
    for name in (
        "mcam_decode_seconds_count",
        "mcam_encode_seconds_count",
        "mcam_queue_wait_seconds_count",
    ):
        assert values[(name, ())] == 1.0, name
    assert values[("mcam_jobs", (("state", "succeeded"),))] == 1.0
    assert values[("mcam_queue_depth", ())] == 0.0
    assert values[("mcam_dead_letters", ())] == 0.0
    assert values[("mcam_queue_up", ())] == 1.0
    posted = (
        "mcam_http_request_duration_seconds_count",
        (("method", "POST"), ("route", "/v1/reconstructions"), ("status", "200")),
    )
    assert values[posted] == 1.0
