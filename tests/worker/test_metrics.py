"""Redis-backed metrics: counters with labels, cumulative histograms, one read for all."""

from __future__ import annotations

import math

import pytest
import redis
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from worker.metrics import BUCKETS_S, COUNTERS, HISTOGRAMS, Metrics, read_metrics


def families(client: redis.Redis) -> dict[str, object]:
    return {family.name: family for family in read_metrics(client)}


def test_empty_store_reads_zeros(client: redis.Redis) -> None:
    found = families(client)
    assert set(found) == set(COUNTERS) | set(HISTOGRAMS)
    hist = found["decode_seconds"].samples[0]
    assert hist.count == 0 and hist.buckets[-1] == (math.inf, 0.0)
    assert found["dead_letters_total"].samples[0].value == 0


def test_counters_with_and_without_labels(client: redis.Redis) -> None:
    metrics = Metrics(client)
    metrics.inc("dead_letters_total")
    metrics.inc("dead_letters_total", 2)
    metrics.inc("frames_dropped_total", 3, device="cam1")
    metrics.inc("frames_dropped_total", 1, device="cam2")
    found = families(client)
    assert found["dead_letters_total"].samples[0].value == 3
    dropped = {s.labels["device"]: s.value for s in found["frames_dropped_total"].samples}
    assert dropped == {"cam1": 3, "cam2": 1}


def test_unknown_names_and_missing_label_rejected(client: redis.Redis) -> None:
    metrics = Metrics(client)
    with pytest.raises(KeyError):
        metrics.observe("nope_seconds", 1.0)
    with pytest.raises(KeyError):
        metrics.inc("nope_total")
    with pytest.raises(KeyError):
        metrics.inc("frames_dropped_total")


@settings(
    max_examples=20, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(st.lists(st.floats(min_value=0, max_value=100, allow_nan=False), max_size=30))
def test_histogram_is_cumulative_and_consistent(client: redis.Redis, values: list[float]) -> None:
    client.flushdb()  # the fixture is shared by the examples: start each from empty
    metrics = Metrics(client)
    for value in values:
        metrics.observe("encode_seconds", value)
    sample = families(client)["encode_seconds"].samples[0]
    assert sample.count == len(values)
    assert sample.value == pytest.approx(sum(values), abs=1e-6)
    counts = [count for _bound, count in sample.buckets]
    assert counts == sorted(counts) and counts[-1] == len(values)
    for bound, count in sample.buckets[:-1]:
        assert count == sum(v <= bound for v in values)
    assert [b for b, _ in sample.buckets] == [*BUCKETS_S, math.inf]
