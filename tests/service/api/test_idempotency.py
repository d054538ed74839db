"""The Idempotency-Key header of the job-creating POSTs, and GET /v1/jobs?idempotency_key=,
against a live API and a real Redis (no worker: the jobs stay queued, and the ``jobs``
stream's length counts them)."""

from __future__ import annotations

import json
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import httpx
import pytest

from service.core.config import Settings
from service.core.security import key_id
from service.main import create_app
from tests.service.conftest import (
    FULL_KEY,
    READ_KEY,
    SUBMIT_KEY,
    frame_png,
    make_settings,
    npy_bytes,
    serve,
)
from worker.embedded_redis import connect
from worker.redis_keys import JOBS_STREAM, idempotency_key, job_key

Client = Callable[..., httpx.Client]
KEY = "8e03978e-40d5-43e8-bc93-6894a57f9324"


def post_frame(
    http: httpx.Client, key: str | bytes | None, data: bytes | None = None, **fields: str
) -> httpx.Response:
    """POST a 32 x 32 PNG frame (or ``data``) to /v1/reconstructions with ``key``."""
    headers = {} if key is None else {"Idempotency-Key": key}
    body = frame_png(32)[0] if data is None else data
    return http.post(
        "/v1/reconstructions", files={"file": ("frame.png", body, "image/png")},
        data={"decoder": "itoh", **fields}, headers=headers,
    )  # fmt: skip


def queued(settings: Settings) -> int:
    """Jobs in the queue's stream."""
    assert settings.redis_url is not None
    return int(connect(settings.redis_url).xlen(JOBS_STREAM))


def test_a_repeat_gets_the_first_job_and_queues_nothing(
    client: Client, settings: Settings
) -> None:
    http = client()
    first = post_frame(http, KEY)
    assert first.status_code == 202, first.text
    again = post_frame(http, f'"{KEY}"')  # the draft's quoted form: the same key
    assert again.status_code == 202, again.text
    assert again.json() == first.json()
    assert again.headers["Location"] == first.headers["Location"]
    assert queued(settings) == 1
    other = post_frame(http, "another key")
    assert other.status_code == 202 and other.json()["id"] != first.json()["id"]
    assert queued(settings) == 2


def test_a_repeated_video_gets_the_first_job(client: Client, settings: Settings) -> None:
    clip = npy_bytes(frame_png(32)[1][None].repeat(2, axis=0))
    fields = {"outputs": "sdr", "encoding": "mantissa", "alpha": "2", "bits": "8"}
    http = client()
    first, again = (
        http.post("/v1/videos", files={"file": ("clip.npy", clip)}, data=fields,
                  headers={"Idempotency-Key": KEY})
        for _ in range(2)
    )  # fmt: skip
    assert first.status_code == again.status_code == 202, (first.text, again.text)
    assert again.json() == first.json()
    assert queued(settings) == 1


@pytest.mark.parametrize(
    "change",
    [{"fields": {"decoder": "herraez"}}, {"data": "other file"}, {"route": "/v1/videos"}],
    ids=["parameters", "file", "route"],
)
def test_a_key_sent_again_with_another_request_is_422(
    client: Client, settings: Settings, change: dict
) -> None:
    http = client()
    assert post_frame(http, KEY).status_code == 202
    if "route" in change:
        data = npy_bytes(frame_png(32)[1][None].repeat(2, axis=0))
        reply = http.post(change["route"], files={"file": ("clip.npy", data)},
                          headers={"Idempotency-Key": KEY})
    elif "data" in change:
        reply = post_frame(http, KEY, data=frame_png(16)[0])
    else:
        reply = post_frame(http, KEY, **change["fields"])
    assert reply.status_code == 422, reply.text
    body = reply.json()
    assert body["code"] == "idempotency_key_reused"
    assert "send a new key for a new job" in body["message"]
    assert queued(settings) == 1


def test_a_key_sent_again_with_the_file_renamed_is_422_saying_so(
    client: Client, settings: Settings
) -> None:
    """The same bytes under another file name (which may say the frame's format) are
    another request: the 422 said "another file" of the very file sent before."""
    http = client()
    assert post_frame(http, KEY).status_code == 202
    renamed = http.post(
        "/v1/reconstructions", files={"file": ("frame-2.png", frame_png(32)[0], "image/png")},
        data={"decoder": "itoh"}, headers={"Idempotency-Key": KEY},
    )  # fmt: skip
    assert renamed.status_code == 422, renamed.text
    assert renamed.json()["code"] == "idempotency_key_reused"
    assert "another file or file name" in renamed.json()["message"]
    assert queued(settings) == 1


@pytest.mark.parametrize(
    ("key", "problem"),
    [("", "is empty"), ('""', "is empty"), ("k" * 256, "has 256 characters"),
     ("caméra".encode(), "holds characters other than printable ASCII"),
     ("a\tb", "holds characters other than printable ASCII")],
    ids=["empty", "empty-quoted", "too-long", "not-ascii", "control"],
)  # fmt: skip
def test_a_bad_key_is_400_saying_what_a_key_is(
    client: Client, settings: Settings, key: str | bytes, problem: str
) -> None:
    reply = post_frame(client(), key)
    assert reply.status_code == 400, reply.text
    body = reply.json()
    assert body["code"] == "invalid_idempotency_key"
    assert body["message"].startswith(f"the Idempotency-Key {problem}")
    assert "1-255 printable ASCII characters" in body["message"]
    assert queued(settings) == 0


def test_a_key_sent_on_two_lines_naming_two_keys_is_400(
    client: Client, settings: Settings
) -> None:
    """Two Idempotency-Key lines: the first was taken and the other, never remembered,
    found no job; the same key on both lines (quoted or not) is one key."""
    http = client()
    files = {"file": ("frame.png", frame_png(32)[0], "image/png")}
    two = http.post("/v1/reconstructions", files=files, data={"decoder": "itoh"},
                    headers=[("Idempotency-Key", KEY), ("Idempotency-Key", "other")])
    assert two.status_code == 400, two.text
    assert two.json()["code"] == "invalid_idempotency_key"
    assert two.json()["message"].startswith("the Idempotency-Key header came 2 times with "
                                            "different keys ('8e03978e-")
    assert queued(settings) == 0
    same = http.post("/v1/reconstructions", files=files, data={"decoder": "itoh"},
                     headers=[("Idempotency-Key", KEY), ("Idempotency-Key", f'"{KEY}"')])
    assert same.status_code == 202, same.text
    assert post_frame(http, KEY).json()["id"] == same.json()["id"]


def test_a_key_of_255_characters_is_taken(client: Client) -> None:
    assert post_frame(client(), "k" * 255).status_code == 202


def test_keys_are_scoped_to_the_api_key(client: Client, settings: Settings) -> None:
    mine, theirs = post_frame(client(), KEY), post_frame(client(SUBMIT_KEY), KEY)
    assert mine.status_code == theirs.status_code == 202
    assert mine.json()["id"] != theirs.json()["id"]
    assert queued(settings) == 2
    found = client().get("/v1/jobs", params={"idempotency_key": KEY})
    assert found.status_code == 200 and found.json()["id"] == mine.json()["id"]
    theirs_found = client(SUBMIT_KEY).get("/v1/jobs", params={"idempotency_key": KEY})
    assert theirs_found.status_code == 200, theirs_found.text
    assert theirs_found.json()["id"] == theirs.json()["id"]
    assert client(READ_KEY).get("/v1/jobs", params={"idempotency_key": KEY}).status_code == 403


def test_a_key_whose_job_expired_makes_a_new_job(client: Client, settings: Settings) -> None:
    """A job's record gone before its key (a retention lowered since the job was queued):
    a repeat makes the job again instead of a 404 for the old one as long as the key
    lives, however often the client sends it again."""
    assert settings.redis_url is not None
    http = client()
    first = post_frame(http, KEY).json()
    connect(settings.redis_url).delete(job_key(first["id"]))
    again = post_frame(http, KEY)
    assert again.status_code == 202, again.text
    assert again.json()["id"] != first["id"]
    found = http.get("/v1/jobs", params={"idempotency_key": KEY})
    assert found.status_code == 200 and found.json()["id"] == again.json()["id"]
    assert queued(settings) == 2


def test_a_key_outlives_a_retention_shorter_than_its_ttl(tmp_path: Path, redis_url: str) -> None:
    """The key lasts MCAM_IDEMPOTENCY_TTL_S from its job's queueing, however short the
    retention (which counts from the job's end): capped at it, the key expired while the
    job still waited in the queue, and a repeat made a second job."""
    settings = make_settings(tmp_path, redis_url, result_retention_s=60)
    with serve(create_app(settings)) as url, httpx.Client(
        base_url=url, headers={"Authorization": f"Bearer {FULL_KEY}"}, timeout=60
    ) as http:
        assert post_frame(http, KEY).status_code == 202
    ttl_s = connect(redis_url).ttl(idempotency_key(key_id(FULL_KEY), KEY))
    assert settings.idempotency_ttl_s - 60 < ttl_s <= settings.idempotency_ttl_s


def test_the_lookup_finds_the_job_or_says_there_is_none(client: Client) -> None:
    http = client()
    job = post_frame(http, KEY).json()
    found = http.get("/v1/jobs", params={"idempotency_key": KEY})
    assert found.status_code == 200, found.text
    assert found.json()["id"] == job["id"] and found.json()["state"] == "queued"
    assert found.json()["links"]["self"] == job["url"]
    missing = http.get("/v1/jobs", params={"idempotency_key": "never sent"})
    assert missing.status_code == 404
    assert "no request with this Idempotency-Key" in missing.json()["message"]
    assert "no job was made for it" not in missing.json()["message"]
    assert "the other routes take no key" in missing.json()["message"]
    bad = http.get("/v1/jobs", params={"idempotency_key": ""})
    assert bad.status_code == 400 and bad.json()["code"] == "invalid_idempotency_key"


def test_a_key_whose_request_is_being_handled_is_409(
    client: Client, settings: Settings
) -> None:
    """A repeat (and the lookup) while the first request holds the key, before its job is
    queued: 409 with Retry-After; the repeat's body is not needed to say so."""
    assert settings.redis_url is not None
    store = connect(settings.redis_url)
    store.set(idempotency_key(key_id(FULL_KEY), KEY), json.dumps({"pending": "elsewhere"}))
    http = client()
    for reply in (post_frame(http, KEY), http.get("/v1/jobs", params={"idempotency_key": KEY})):
        assert reply.status_code == 409, reply.text
        assert reply.json()["code"] == "idempotency_key_in_use"
        assert reply.headers["Retry-After"] == "1"
    assert queued(settings) == 0


def test_a_refused_request_gives_its_key_back(client: Client, settings: Settings) -> None:
    """A request refused (an unknown decoder) made no job: a retry with the key, mended,
    makes it."""
    http = client()
    refused = post_frame(http, KEY, decoder="no-such-decoder")
    assert refused.status_code == 422 and refused.json()["code"] != "idempotency_key_reused"
    assert http.get("/v1/jobs", params={"idempotency_key": KEY}).status_code == 404
    assert post_frame(http, KEY).status_code == 202
    assert queued(settings) == 1


def test_requests_sent_at_once_with_one_key_make_one_job(
    client: Client, settings: Settings
) -> None:
    """Each answer is the one job (202) or 409 idempotency_key_in_use, never a second job."""
    http = client()
    with ThreadPoolExecutor(4) as pool:
        replies = list(pool.map(lambda _: post_frame(http, KEY), range(4)))
    accepted = {reply.json()["id"] for reply in replies if reply.status_code == 202}
    refused = [reply.json()["code"] for reply in replies if reply.status_code != 202]
    assert len(accepted) == 1 and set(refused) <= {"idempotency_key_in_use"}
    assert queued(settings) == 1


def test_the_header_is_in_the_openapi_document(client: Client) -> None:
    paths = client().get("/openapi.json").json()["paths"]
    for path in ("/v1/reconstructions", "/v1/videos"):
        (header,) = [p for p in paths[path]["post"]["parameters"]
                     if p["name"] == "Idempotency-Key"]  # fmt: skip
        assert header["in"] == "header" and "never a second one" in header["description"]
    assert "idempotency_key" in [p["name"] for p in paths["/v1/jobs"]["get"]["parameters"]]


def test_the_openapi_document_lists_the_keys_errors_on_both_posts(client: Client) -> None:
    paths = client().get("/openapi.json").json()["paths"]
    for path in ("/v1/reconstructions", "/v1/videos"):
        responses = paths[path]["post"]["responses"]
        for status, code in (("400", "invalid_idempotency_key"),
                             ("409", "idempotency_key_in_use"),
                             ("422", "idempotency_key_reused")):  # fmt: skip
            assert code in responses[status]["description"], (path, status)
