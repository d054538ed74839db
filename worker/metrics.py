"""Counters and histograms kept in Redis, so every worker process adds to the same numbers.

Usage (worker side)::

    metrics = Metrics(client)
    metrics.observe("decode_seconds", 0.012)
    metrics.inc("dead_letters_total")
    metrics.inc("frames_dropped_total", 3, device="cam1")

Usage (API side, for a Prometheus collector)::

    for family in read_metrics(client):   # list[MetricFamily]
        family.name, family.kind, family.help, family.samples  # kind: "counter" | "histogram"

Histogram samples are cumulative like Prometheus: ``buckets`` is a list of
``(upper_bound_s, count_of_observations <= bound)`` ending with ``inf``. Names are
without the ``mcam_`` prefix; the collector adds it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import redis

from worker.redis_keys import METRICS_PREFIX

#: Upper bounds in seconds shared by all histograms.
BUCKETS_S: tuple[float, ...] = (
    0.001,
    0.0025,
    0.005,
    0.01,
    0.025,
    0.05,
    0.1,
    0.25,
    0.5,
    1.0,
    2.5,
    5.0,
    10.0,
    30.0,
    60.0,
)

HISTOGRAMS: dict[str, str] = {
    "queue_wait_seconds": "time a job or frame waited in the queue before a worker took it",
    "decode_seconds": "time to decode one frame (predict winding + invert)",
    "encode_seconds": "time to encode and durably write one job's or frame's results",
    "total_seconds": "time from submission to the durable result",
}

#: Counter name -> (help, label name or "" when unlabelled).
COUNTERS: dict[str, tuple[str, str]] = {
    "jobs_processed_total": (
        "jobs that ended, by final state (succeeded, failed, or cancelled)", "state"
    ),
    "jobs_rejected_total": (
        "job submissions refused by a queue bound: queue_full (jobs), queue_bytes, or the "
        "API key's own key_jobs or key_bytes",
        "reason",
    ),
    "frames_processed_total": ("device frames reconstructed, by device", "device"),
    "frames_dropped_total": (
        "device frames dropped because the device's stream was full (oldest dropped)",
        "device",
    ),
    "dead_letters_total": ("stream entries moved to the dead-letter stream", ""),
    "redeliveries_total": ("stream entries reclaimed from a consumer that stopped", ""),
    "jobs_abandoned_total": (
        "jobs a stalled worker stopped because another worker had taken them over", ""
    ),
}


def histogram_key(name: str) -> str:
    """Hash ``metrics:hist:<name>``: one field per bucket bound, plus ``sum`` and ``count``."""
    return f"{METRICS_PREFIX}hist:{name}"


def counter_key(name: str) -> str:
    """Hash ``metrics:counter:<name>``: one field per label value ('' when unlabelled)."""
    return f"{METRICS_PREFIX}counter:{name}"


def _bucket_field(seconds: float) -> str:
    for bound in BUCKETS_S:
        if seconds <= bound:
            return repr(bound)
    return "inf"


@dataclass(frozen=True)
class Sample:
    """One time series: its labels and value (a histogram's value is the sum of its
    observations in s, ``buckets`` the cumulative counts and ``count`` their number)."""

    labels: dict[str, str]
    value: float = 0.0
    buckets: list[tuple[float, float]] = field(default_factory=list)
    count: float = 0.0


@dataclass(frozen=True)
class MetricFamily:
    """All samples of one metric; ``kind`` is ``counter`` or ``histogram``."""

    name: str
    kind: str
    help: str
    samples: list[Sample]


class Metrics:
    """Writes counters and histogram observations to Redis (atomic increments)."""

    def __init__(self, client: redis.Redis) -> None:
        self.client = client

    def observe(self, name: str, seconds: float, pipe: redis.client.Pipeline | None = None,
                times: int = 1) -> None:
        """Add an observation of ``seconds`` to histogram ``name``, ``times`` times (the
        frames of a video, each observed at the mean of its decode)."""
        if name not in HISTOGRAMS:
            raise KeyError(f"unknown histogram {name!r}")
        target = pipe if pipe is not None else self.client.pipeline(transaction=False)
        key = histogram_key(name)
        target.hincrby(key, _bucket_field(seconds), times)
        target.hincrbyfloat(key, "sum", float(seconds) * times)
        target.hincrby(key, "count", times)
        if pipe is None:
            target.execute()

    def inc(
        self,
        name: str,
        amount: int = 1,
        pipe: redis.client.Pipeline | None = None,
        **labels: str,
    ) -> None:
        """Add ``amount`` to counter ``name``; give its one label as a keyword if it has one."""
        if name not in COUNTERS:
            raise KeyError(f"unknown counter {name!r}")
        label = COUNTERS[name][1]
        value = str(labels[label]) if label else ""
        (pipe if pipe is not None else self.client).hincrby(counter_key(name), value, amount)


def forget_label(pipe: redis.client.Pipeline, label: str, value: str) -> None:
    """Queue on ``pipe`` the removal of every counter's series labelled ``label`` =
    ``value`` (a forgotten device's ``frames_processed_total`` and
    ``frames_dropped_total``), so that label values that come and go do not pile up."""
    for name, (_help, counter_label) in COUNTERS.items():
        if counter_label == label:
            pipe.hdel(counter_key(name), value)


def _read_histogram(raw: dict[bytes, bytes]) -> Sample:
    counts = {k.decode(): float(v) for k, v in raw.items()}
    running = 0.0
    buckets: list[tuple[float, float]] = []
    for bound in BUCKETS_S:
        running += counts.get(repr(bound), 0.0)
        buckets.append((bound, running))
    buckets.append((math.inf, counts.get("count", 0.0)))
    return Sample(
        labels={}, value=counts.get("sum", 0.0), buckets=buckets, count=counts.get("count", 0.0)
    )


def read_metrics(client: redis.Redis) -> list[MetricFamily]:
    """Every counter and histogram, read in one round trip (missing ones read as zero)."""
    pipe = client.pipeline(transaction=False)
    for name in COUNTERS:
        pipe.hgetall(counter_key(name))
    for name in HISTOGRAMS:
        pipe.hgetall(histogram_key(name))
    replies = pipe.execute()
    families: list[MetricFamily] = []
    for (name, (help_text, label)), raw in zip(COUNTERS.items(), replies, strict=False):
        samples = [
            Sample(labels={label: k.decode()} if label else {}, value=float(v))
            for k, v in sorted(raw.items())
        ]
        if not label and not samples:
            samples = [Sample(labels={}, value=0.0)]
        families.append(MetricFamily(name, "counter", help_text, samples))
    for name, raw in zip(HISTOGRAMS, replies[len(COUNTERS) :], strict=True):
        families.append(MetricFamily(name, "histogram", HISTOGRAMS[name], [_read_histogram(raw)]))
    return families
