"""Tests of service/api/downloads.py: stored results sent whole, or refused cleanly,
whatever the retention purge does meanwhile."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest
from fastapi import FastAPI

from service.api.downloads import stored_file
from service.api.errors import install_error_handlers
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


@pytest.fixture
def api_download(store: ResultStore) -> Iterator[httpx.Client]:
    """A live app with the API's error handlers whose route sends the stored result."""
    app = FastAPI()
    install_error_handlers(app)

    @app.get("/result")
    def result() -> object:
        return stored_file(store, KEY, "image/x-exr", "r.exr")

    with serve(app) as url, httpx.Client(base_url=url) as client:
        yield client


def test_a_range_in_another_unit_is_ignored(api_download: httpx.Client) -> None:
    """RFC 9110 14.2: a server ignores a range unit it does not understand; it was 400."""
    whole = api_download.get("/result", headers={"Range": "items=0-1"})
    assert whole.status_code == 200 and whole.content == DATA


@pytest.mark.parametrize(
    "value",
    [
        "bytes=abc", "bytes=5-2", "bytes", "bytes=,",
        # a malformed range beside a good one: Starlette left it out, a 206 of bytes 0-9
        "bytes=0-9,-", "bytes=0-9,abc", "bytes=0-9,5", "bytes=0 - 9", "bytes=0-9,-x",
        f"bytes={len(DATA)}-,-",  # malformed before unsatisfiable (it was a 416)
    ],
)  # fmt: skip
def test_a_malformed_range_is_a_json_400(api_download: httpx.Client, value: str) -> None:
    """RFC 9110 14.2: a server may reject a Range with an invalid range set; one
    malformed range makes the set malformed, as ``bytes=0-9,5-2`` always did."""
    reply = api_download.get("/result", headers={"Range": value})
    assert reply.status_code == 400, reply.text
    assert reply.headers["content-type"] == "application/json"  # it was text/plain
    assert reply.json()["code"] == "bad_range" and "bytes=FIRST-LAST" in reply.json()["message"]


def test_a_range_past_the_end_is_a_json_416(api_download: httpx.Client) -> None:
    reply = api_download.get("/result", headers={"Range": f"bytes={len(DATA)}-"})
    assert reply.status_code == 416, reply.text
    assert reply.headers["content-type"] == "application/json"  # it was text/plain
    assert reply.headers["content-range"] == f"bytes */{len(DATA)}"
    assert reply.json()["code"] == "range_not_satisfiable"
    assert f"0-{len(DATA) - 1}" in reply.json()["message"]


@pytest.mark.parametrize(
    ("ranges", "sent"),
    [(f"0-1,{len(DATA)}-", DATA[0:2]), (f"{len(DATA) + 5}-,-3", DATA[-3:]), ("0-1,-0", DATA[0:2])],
)
def test_a_range_set_with_one_satisfiable_range_sends_that_range(
    api_download: httpx.Client, ranges: str, sent: bytes
) -> None:
    """RFC 9110 14.1.1: a range set is satisfiable if any of its ranges is; one range
    past the end made the whole set a 416."""
    reply = api_download.get("/result", headers={"Range": f"bytes={ranges}"})
    assert reply.status_code == 206, reply.text
    assert reply.content == sent


def test_empty_elements_of_a_range_set_are_ignored(api_download: httpx.Client) -> None:
    """RFC 9110 5.6.1.2: a list's empty elements are ignored, not malformed."""
    reply = api_download.get("/result", headers={"Range": "bytes=0-9,, 20-29 ,"})
    assert reply.status_code == 206, reply.text
    assert reply.headers["content-type"].startswith("multipart/byteranges")
    assert DATA[0:10] in reply.content and DATA[20:30] in reply.content


@pytest.mark.parametrize("ranges", [f"{len(DATA)}-,-0", "-0"])
def test_a_range_set_with_no_satisfiable_range_is_a_416(
    api_download: httpx.Client, ranges: str
) -> None:
    """``bytes=-0`` (the last 0 bytes) was told it asked for bytes past the end."""
    reply = api_download.get("/result", headers={"Range": f"bytes={ranges}"})
    assert reply.status_code == 416, reply.text
    assert reply.json()["code"] == "range_not_satisfiable"
    assert "asks for no byte of this" in reply.json()["message"]


def test_a_matching_if_none_match_is_a_304_without_the_file(api_download: httpx.Client) -> None:
    first = api_download.get("/result")
    etag = first.headers["etag"]
    for tag in (etag, f'"other", {etag}', f"W/{etag}", "*"):
        again = api_download.get("/result", headers={"If-None-Match": tag})
        assert again.status_code == 304 and again.content == b""
        assert again.headers["etag"] == etag
        assert again.headers["cache-control"] == first.headers["cache-control"]


def test_another_if_none_match_sends_the_file(api_download: httpx.Client) -> None:
    again = api_download.get("/result", headers={"If-None-Match": '"other"'})
    assert again.status_code == 200 and again.content == DATA


def test_if_modified_since_is_a_304_only_for_a_file_not_changed_since(
    api_download: httpx.Client,
) -> None:
    modified = api_download.get("/result").headers["last-modified"]
    same = api_download.get("/result", headers={"If-Modified-Since": modified})
    assert same.status_code == 304 and same.content == b""
    before = "Mon, 01 Jan 2001 00:00:00 GMT"
    assert api_download.get("/result", headers={"If-Modified-Since": before}).status_code == 200
    garbled = api_download.get("/result", headers={"If-Modified-Since": "yesterday"})
    assert garbled.status_code == 200 and garbled.content == DATA


def test_if_none_match_wins_over_if_modified_since(api_download: httpx.Client) -> None:
    modified = api_download.get("/result").headers["last-modified"]
    headers = {"If-None-Match": '"other"', "If-Modified-Since": modified}
    assert api_download.get("/result", headers=headers).status_code == 200


def test_an_if_match_naming_another_file_is_a_412(api_download: httpx.Client) -> None:
    """RFC 9110 13.1.1: a client that fetches pieces of one file (a device's newest frame
    changes) with If-Match got 200 or 206 from whatever file was there, mixing files."""
    etag = api_download.get("/result").headers["etag"]
    for tag in ('"other"', f"W/{etag}"):  # If-Match compares strongly
        for extra in ({}, {"Range": "bytes=0-9"}):
            reply = api_download.get("/result", headers={"If-Match": tag, **extra})
            assert reply.status_code == 412, reply.text
            assert reply.json()["code"] == "precondition_failed"
            assert etag in reply.json()["message"]
    for tag in (etag, f'"other", {etag}', "*"):
        reply = api_download.get("/result", headers={"If-Match": tag, "Range": "bytes=0-9"})
        assert reply.status_code == 206 and reply.content == DATA[:10]


def test_entity_tags_on_several_header_lines_are_one_list(api_download: httpx.Client) -> None:
    """RFC 9110 5.3: several lines of a header are one comma-separated list. Only the
    first line was read: a second ``If-Match`` line naming the file's tag got 412, a
    second ``If-None-Match`` line naming it got the file again."""
    etag = api_download.get("/result").headers["etag"]
    if_match = [("If-Match", '"other"'), ("If-Match", etag), ("Range", "bytes=0-9")]
    reply = api_download.get("/result", headers=if_match)
    assert reply.status_code == 206 and reply.content == DATA[:10], reply.text
    if_none_match = [("If-None-Match", '"other"'), ("If-None-Match", etag)]
    again = api_download.get("/result", headers=if_none_match)
    assert again.status_code == 304 and again.content == b""
    neither = [("If-Match", '"other"'), ("If-Match", '"another"')]
    assert api_download.get("/result", headers=neither).status_code == 412


def test_if_unmodified_since_before_the_file_changed_is_a_412(
    api_download: httpx.Client,
) -> None:
    modified = api_download.get("/result").headers["last-modified"]
    before = api_download.get(
        "/result", headers={"If-Unmodified-Since": "Mon, 01 Jan 2001 00:00:00 GMT"}
    )
    assert before.status_code == 412 and before.json()["code"] == "precondition_failed"
    for since in (modified, "yesterday"):
        reply = api_download.get("/result", headers={"If-Unmodified-Since": since})
        assert reply.status_code == 200 and reply.content == DATA
    etag = api_download.get("/result").headers["etag"]
    headers = {"If-Match": etag, "If-Unmodified-Since": "Mon, 01 Jan 2001 00:00:00 GMT"}
    assert api_download.get("/result", headers=headers).status_code == 200
