"""Prometheus metrics: this process's request durations plus the queue's shared numbers.

Request durations are kept per API process (labelled by route template, never
the raw path). Queue-wait, decode and encode histograms and the counters come
from Redis (:mod:`worker.metrics`), so every worker's observations are included;
queue depth, jobs by state and dead letters are read at scrape time.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable, Iterator

import redis
from prometheus_client import CollectorRegistry, Histogram
from prometheus_client.core import (
    CounterMetricFamily,
    GaugeMetricFamily,
    HistogramMetricFamily,
    Metric,
)
from prometheus_client.registry import Collector
from starlette.routing import BaseRoute
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from service.api.route_match import route_template
from service.api.state import ServiceState
from worker.jobs import JobState
from worker.metrics import MetricFamily, read_metrics

log = logging.getLogger(__name__)
PREFIX = "mcam_"


def _bound(value: float) -> str:
    return "+Inf" if math.isinf(value) else repr(value)


def _worker_family(family: MetricFamily) -> Metric:
    name = PREFIX + family.name
    labels = sorted({key for sample in family.samples for key in sample.labels})
    if family.kind == "histogram":
        metric: Metric = HistogramMetricFamily(name, family.help, labels=labels)
        for sample in family.samples:
            buckets = [(_bound(bound), count) for bound, count in sample.buckets]
            metric.add_metric([sample.labels[k] for k in labels], buckets, sample.value)
        return metric
    metric = CounterMetricFamily(name, family.help, labels=labels)
    for sample in family.samples:
        metric.add_metric([sample.labels[k] for k in labels], sample.value)
    return metric


class QueueCollector(Collector):
    """Reads the Redis-backed metrics and the queue's statistics at every scrape."""

    def __init__(self, state: Callable[[], ServiceState]) -> None:
        self.state = state

    def collect(self) -> Iterator[Metric]:
        up = GaugeMetricFamily(PREFIX + "queue_up", "1 when Redis answered this scrape")
        try:
            state = self.state()
            families = read_metrics(state.client)
            stats = state.queue.stats()
            memory = state.client.info("memory")
        except redis.exceptions.RedisError as exc:
            log.warning("metrics scrape without queue numbers: %s", exc)
            up.add_metric([], 0)
            yield up
            return
        up.add_metric([], 1)
        yield up
        yield from (_worker_family(family) for family in families)
        yield GaugeMetricFamily(
            PREFIX + "queue_depth",
            "jobs in the jobs stream that no worker has taken yet",
            value=max(stats["stream_depth"] - stats["pending"], 0),
        )
        yield GaugeMetricFamily(
            PREFIX + "queue_pending",
            "jobs a worker has taken and not finished (running, or to be reclaimed)",
            value=stats["pending"],
        )
        yield GaugeMetricFamily(
            PREFIX + "queue_held_bytes",
            "bytes of codes in the jobs stream (API submits stop at MCAM_JOBS_MAX_BYTES)",
            value=stats["held_bytes"],
        )
        yield GaugeMetricFamily(
            PREFIX + "redis_used_memory_bytes",
            "memory Redis uses; at mcam_redis_maxmemory_bytes it refuses writes (503 store_full)",
            value=memory["used_memory"],
        )
        yield GaugeMetricFamily(
            PREFIX + "redis_maxmemory_bytes",
            "Redis's maxmemory (0: unbounded; the embedded one's is MCAM_REDIS_MAXMEMORY)",
            value=memory["maxmemory"],
        )
        yield GaugeMetricFamily(
            PREFIX + "dead_letter_stream_length",
            "entries in the dead-letter stream now (mcam_dead_letters_total counts every one)",
            value=stats["dead_letters"],
        )
        jobs = GaugeMetricFamily(
            PREFIX + "jobs_active",
            "jobs queued or running now, by state (mcam_jobs_processed_total counts ended ones)",
            labels=["state"],
        )
        for state in (JobState.QUEUED, JobState.RUNNING):
            jobs.add_metric([state.value], stats["jobs_by_state"][state.value])
        yield jobs
        devices = GaugeMetricFamily(
            PREFIX + "device_stream_depth",
            "frames in each device's stream not yet stored (waiting, or being decoded)",
            labels=["device"],
        )
        for device, info in stats["devices"].items():
            devices.add_metric([device], info["depth"])
        yield devices


def build_registry(state: Callable[[], ServiceState]) -> tuple[CollectorRegistry, Histogram]:
    """A registry for one app: the request histogram and the queue collector (which asks
    ``state()`` for the running process's state at each scrape)."""
    registry = CollectorRegistry()
    requests = Histogram(
        PREFIX + "http_request_duration_seconds",
        "API request durations by method, route template and status",
        ["method", "route", "status"],
        registry=registry,
    )
    registry.register(QueueCollector(state))
    return registry, requests


#: Methods kept as metric labels; any other (a client may send any token) is "other",
#: so that made-up methods cannot grow the label set without bound.
HTTP_METHODS = frozenset({"GET", "HEAD", "POST", "PUT", "PATCH", "DELETE", "OPTIONS"})


class RequestTimer:
    """ASGI middleware observing each HTTP request's duration into ``histogram``, by
    method (as the client sent it: HEAD is answered as a GET inside), route template
    and status. The template is the router's, else the one of the API ``routes`` the
    path is for (a body refused before routing, a wrong method), else ``unmatched``."""

    def __init__(self, app: ASGIApp, histogram: Histogram, routes: list[BaseRoute]) -> None:
        self.app = app
        self.histogram = histogram
        self.routes = routes

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        start = time.perf_counter()
        status = 500

        async def timed_send(message: Message) -> None:
            nonlocal status
            if message["type"] == "http.response.start":
                status = message["status"]
            await send(message)

        try:
            await self.app(scope, receive, timed_send)
        finally:
            route = getattr(scope.get("route"), "path", None)
            route = route_template(self.routes, scope) if route is None else route or "/"
            route = "unmatched" if route is None else route
            method = scope["method"] if scope["method"] in HTTP_METHODS else "other"
            self.histogram.labels(method, route, str(status)).observe(
                time.perf_counter() - start
            )
