"""Tests of service/api/downloads.py: stored results sent whole, or refused cleanly,
whatever the retention purge does meanwhile."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest
from fastapi import FastAPI

from service.api.downloads import stored_file
from tests.service.conftest import serve
from worker.result_store import ResultNotFoundError, ResultStore

KEY = "jobs/abc/result.exr"
DATA = bytes(range(256)) * 400


@pytest.fixture
def store(tmp_path: Path) -> ResultStore:
    store = ResultStore(tmp_path / "results", retention_s=3600)
    store.write(KEY, DATA)
    return store


@pytest.fixture
def purged_on_the_way(store: ResultStore) -> Iterator[httpx.Client]:
    """A live app whose route builds the download, then the purge removes the file
    before the response is sent (the race that gave 500s, and 200s cut off after the
    headers)."""
    app = FastAPI()

    @app.get("/result")
    def result() -> object:
        response = stored_file(store, KEY, "image/x-exr", "r.exr")
        store.delete(KEY)
        return response

    with serve(app) as url, httpx.Client(base_url=url) as client:
        yield client


def test_a_result_purged_after_it_was_opened_is_sent_whole(
    store: ResultStore, purged_on_the_way: httpx.Client
) -> None:
    whole = purged_on_the_way.get("/result")
    assert whole.status_code == 200 and whole.content == DATA
    assert whole.headers["content-length"] == str(len(DATA))
    assert not store.exists(KEY)


def test_a_range_of_a_purged_result_is_sent(purged_on_the_way: httpx.Client) -> None:
    part = purged_on_the_way.get("/result", headers={"Range": "bytes=100-199"})
    assert part.status_code == 206 and part.content == DATA[100:200]


def test_a_result_purged_before_it_was_opened_is_not_found(store: ResultStore) -> None:
    store.delete(KEY)
    with pytest.raises(ResultNotFoundError, match="never written or expired"):
        stored_file(store, KEY, "image/x-exr", "r.exr")
