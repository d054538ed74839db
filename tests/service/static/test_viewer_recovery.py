"""The web viewer when things go wrong, in headless Debian chromium (Playwright, no download).

Real uvicorn on 127.0.0.1, real Redis, a real worker where a job should run. A job outlives
a server restart, and a job's address opened without a key is followed once it is saved, and
another job's address entered on the page is followed, and one cut short says so; a missing
or unknown key says where on the page the key goes; a 429 is waited out as Retry-After says;
a stuck job is polled gently and can be cancelled, and so is the job of an upload the server
made before Cancel came (found by its Idempotency-Key); a job gone from the server is given
up with a clear message; the result panels show a job's results only once it succeeded,
never beside another job's, and previews asked for again are said to be; a decoder list that
failed says how to list them again. The live device view waits out a 429 too, asks again for
a poll left unanswered, resumes (and lists the devices again) once a key is saved after a
refused one, watches the device again after a reload, stops watching a device the server
forgot, never shows one device's frame or health beside another's, and says why a device
sends nothing (no health report yet, a port that does not open, a silent daemon).
"""

from __future__ import annotations

import re
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING

import anyio
import httpx
import numpy as np
import pytest
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from models.decoders.registry import get_decoder
from models.formation import SensorParams, simulate
from service.api.in_turn import BUSY_RETRY_AFTER_S
from service.api.state import Slots
from service.core.config import Settings
from service.main import create_app
from tests.service.conftest import (
    FULL_KEY,
    SUBMIT_KEY,
    frame_png,
    make_settings,
    npy_bytes,
    running_worker,
    serve,
)
from tests.service.static.conftest import (
    POLL_MS,
    needs_chromium,
    open_viewer,
    wait_for_js,
    wait_for_status,
)
from tests.worker.conftest import overflowing_codes
from worker.embedded_redis import connect
from worker.outputs import encode_exr_result
from worker.redis_keys import DEVICES_SET, JOBS_STREAM, health_key, job_key, latest_key
from worker.result_store import RESULTS_DIR, ResultStore
from worker.runner import Worker

if TYPE_CHECKING:
    from playwright.sync_api import Browser, Page, Route

SIZE = 32  # small frames: the tests are about the page, not the decoder
JOB_ID = re.compile(r"job ([0-9a-f]{32})")
PANELS = "['img-codes', 'img-winding', 'img-hdr']"

pytestmark = [pytest.mark.slow, needs_chromium]


@pytest.fixture
def frame(tmp_path: Path) -> Path:
    path = tmp_path / "frame.png"
    path.write_bytes(frame_png(SIZE)[0])
    return path


def api_requests(page: Page, prefix: str) -> list[str]:
    """The URLs the page requests under ``prefix``, appended as they go out."""
    seen: list[str] = []
    page.on("request", lambda request: seen.append(request.url) if prefix in request.url else None)
    return seen


def submit(page: Page, path: Path) -> str:
    """Upload ``path``, press Run, and return the job id once the status shows it."""
    page.set_input_files("#file", str(path))
    before = page.inner_text("#status")
    page.click("#run")
    wait_for_js(
        page,
        "before => { const now = document.getElementById('status').textContent;"
        " return now !== before && /job [0-9a-f]{32}/.test(now); }",
        arg=before,
    )
    found = JOB_ID.search(page.inner_text("#status"))
    assert found is not None
    return found.group(1)


def panels_empty(page: Page) -> bool:
    """No result image, a blank histogram and no download."""
    return bool(
        page.evaluate(
            f"{PANELS}.every(id => !document.getElementById(id).getAttribute('src'))"
            " && (() => { const shown = document.getElementById('histogram');"
            " const blank = document.createElement('canvas');"
            " blank.width = shown.width; blank.height = shown.height;"
            " return shown.toDataURL() === blank.toDataURL(); })()"
        )
    ) and page.is_disabled("#download")


def wait_for_panels(page: Page) -> None:
    wait_for_js(page, "!document.getElementById('download').disabled")
    wait_for_js(  # blob images decode asynchronously
        page,
        f"{PANELS}.every(id => {{ const image = document.getElementById(id);"
        f" return image.complete && image.naturalWidth === {SIZE}; }})"
    )


def test_a_job_is_followed_across_a_server_restart(
    browser: Browser, settings: Settings, frame: Path
) -> None:
    with serve(create_app(settings)) as url:
        page = open_viewer(browser, url)
        job_id = submit(page, frame)  # no worker yet: the job waits in the queue
        wait_for_status(page, "queued")
    status = wait_for_status(page, "connection to the server lost")
    assert job_id in status and "retrying in" in status
    assert page.get_attribute("#status", "class") == "warning"
    assert page.is_disabled("#run") and page.is_enabled("#cancel")

    port = int(url.rsplit(":", 1)[1])
    with serve(create_app(settings), port), running_worker(settings):
        assert wait_for_status(page, "succeeded") == f"job {job_id}: succeeded"
        wait_for_panels(page)
    assert page.is_enabled("#run") and page.is_disabled("#cancel")


def test_a_job_is_followed_again_after_a_reload_or_back_and_forward(
    browser: Browser, settings: Settings, api: str, frame: Path
) -> None:
    """The job in flight was forgotten by a reload (or leaving the page and coming
    back): the page read "No job yet." while the job ran on, its results out of reach."""
    page = open_viewer(browser, api)
    job_id = submit(page, frame)  # no worker yet: the job waits in the queue
    wait_for_status(page, "queued")
    page.reload()
    assert wait_for_status(page, job_id) == f"job {job_id}: queued"
    assert page.is_disabled("#run") and page.is_enabled("#cancel")
    page.goto("about:blank")
    page.go_back()
    assert wait_for_status(page, job_id) == f"job {job_id}: queued"
    with running_worker(settings):
        assert wait_for_status(page, "succeeded") == f"job {job_id}: succeeded"
        wait_for_panels(page)
    assert page.is_enabled("#run") and page.is_disabled("#cancel")


def test_the_job_in_the_address_is_followed_once_the_key_is_saved(
    browser: Browser, settings: Settings, api: str, frame: Path
) -> None:
    """A ``#job=`` address opened with no key saved asked for the key, and saving it
    listed the decoders only: the job was never followed ("No job yet.")."""
    queued = httpx.post(f"{api}/v1/reconstructions", files={"file": frame.read_bytes()},
                        headers={"Authorization": f"Bearer {FULL_KEY}"}, timeout=60)
    job_id = queued.json()["id"]  # no worker yet: the job waits in the queue
    page = browser.new_page()
    page.goto(f"{api}/#job={job_id}")
    asked = page.inner_text("#status")
    assert asked.startswith("Enter the API key") and f"then job {job_id} is followed" in asked
    page.fill("#api-key", FULL_KEY)
    page.click("#key-form button")
    wait_for_status(page, f"job {job_id}: queued")
    assert page.is_disabled("#run") and page.is_enabled("#cancel")
    with running_worker(settings):
        assert wait_for_status(page, "succeeded") == f"job {job_id}: succeeded"
        wait_for_panels(page)
    assert page.url.endswith(f"#job={job_id}")


def test_another_job_s_address_entered_on_the_page_is_followed(
    browser: Browser, api: str, frame: Path
) -> None:
    """An address naming another job entered while the page was open changes only its
    ``#job=``: the page was not loaded again and went on showing the first job under the
    second's address."""
    page = open_viewer(browser, api)
    first = submit(page, frame)  # no worker: both jobs wait in the queue
    wait_for_status(page, f"job {first}: queued")
    queued = httpx.post(f"{api}/v1/reconstructions", files={"file": frame.read_bytes()},
                        headers={"Authorization": f"Bearer {FULL_KEY}"}, timeout=60)
    second = queued.json()["id"]
    with page.expect_event("load"):  # the page is loaded afresh
        page.evaluate("(id) => { setTimeout(() => { location.hash = `job=${id}`; }); }", second)
    assert wait_for_status(page, second) == f"job {second}: queued"
    assert page.url.endswith(f"#job={second}")
    assert page.is_disabled("#run") and page.is_enabled("#cancel")


def test_an_address_whose_job_id_was_cut_short_says_so(browser: Browser, api: str) -> None:
    """A job's address cut short when copied named no job the page could follow, and the
    page read "No job yet." as if the address named none."""
    page = open_viewer(browser, api)
    page.goto("about:blank")
    page.goto(f"{api}/#job=0123456789abcdef")
    status = wait_for_status(page, "names no job")
    assert "0123456789abcdef" in status and "copy the job's whole address again" in status
    assert page.get_attribute("#status", "class") == "error"


def documented_polls(span_ms: float) -> int:
    """Polls of a job in its first ``span_ms`` as the README says: at once, then after
    250 ms, 1.5 times later each time, up to every 2 s."""
    polls, at, delay = 0, 0.0, 250.0
    while at <= span_ms:
        polls, at, delay = polls + 1, at + delay, min(delay * 1.5, 2000.0)
    return polls


def run_page_clock(page: Page, span_ms: int, step_ms: int = 50) -> None:
    """Move the page's fake clock on by ``span_ms``, ``step_ms`` at a time, each step
    once the page's requests have all finished (a reply arrives in real time; a step
    taken before the page has set its next timer only delays that timer)."""
    pending: list[object] = []
    page.on("request", lambda request: pending.append(request))
    page.on("requestfinished", lambda request: pending.remove(request))
    page.on("requestfailed", lambda request: pending.remove(request))
    for _ in range(span_ms // step_ms):
        page.clock.run_for(step_ms)
        deadline = time.monotonic() + 30
        while pending:
            if time.monotonic() > deadline:
                pytest.fail(f"requests still open after 30 s: {pending}")
            page.wait_for_timeout(5)


def test_a_stuck_job_is_polled_gently_and_can_be_cancelled(
    browser: Browser, api: str, frame: Path
) -> None:
    """Over 20 s of the page's own (fake) time a queued job is polled no more often than
    the documented schedule allows, and at least a few times."""
    page = open_viewer(browser, api, fake_clock=True)
    job_requests = api_requests(page, "/v1/jobs/")
    job_id = submit(page, frame)  # no worker: the job stays queued
    run_page_clock(page, 20_000)
    polls = [url for url in job_requests if url.endswith(f"/v1/jobs/{job_id}")]
    assert 3 <= len(polls) <= documented_polls(20_000), f"{len(polls)} polls in 20 s"
    assert page.inner_text("#status") == f"job {job_id}: queued"
    assert page.is_disabled("#run")
    page.click("#cancel")
    assert wait_for_status(page, "cancelled") == f"job {job_id}: cancelled"
    assert page.is_enabled("#run") and page.is_disabled("#cancel")


def test_panels_show_only_a_succeeded_job(
    browser: Browser, api: str, settings: Settings, frame: Path, tmp_path: Path
) -> None:
    page = open_viewer(browser, api)
    errors: list[str] = []
    page.on("pageerror", lambda exc: errors.append(str(exc)))
    overflow = tmp_path / "overflow.npy"
    overflow.write_bytes(npy_bytes(overflowing_codes(SIZE)))
    with running_worker(settings):
        submit(page, frame)
        wait_for_panels(page)
        page.select_option("#encoding", "mantissa")
        page.fill("#alpha", "1e6")
        page.fill("#bits", "8")
        submit(page, overflow)
        assert "output_overflow" in wait_for_status(page, "failed")
        assert panels_empty(page), "the failed job left the previous job's results on screen"

    page.select_option("#encoding", "")
    page.fill("#alpha", "")
    page.fill("#bits", "")
    wait_for_js(page, "!document.getElementById('run').disabled")
    job_requests = api_requests(page, "/v1/jobs/")
    job_id = submit(page, frame)  # the worker is gone: the job stays queued
    page.fill("#exposure", "-2")
    page.dispatch_event("#exposure", "input")
    page.wait_for_timeout(1_000)
    assert page.inner_text("#status") == f"job {job_id}: queued"
    assert panels_empty(page), "the slider fetched a preview of a job still in the queue"
    assert not any("/result" in url for url in job_requests)
    page.click("#cancel")
    wait_for_status(page, "cancelled")
    assert errors == []


@contextmanager
def previews_refused(
    browser: Browser, redis_url: str, frame: Path, tmp_path: Path
) -> Iterator[tuple[Page, str, Slots]]:
    """A viewer whose job succeeded while the API's one decode turn (MCAM_MAX_CONCURRENT
    _DECODES 1, MCAM_DECODE_WAIT_S 0) was held, so that its previews are refused 503
    server_busy: yields the page, the job id and the turns (release one to end the refusals)
    once a preview was refused, with the worker still running."""
    settings = make_settings(tmp_path, redis_url, max_concurrent_decodes=1, decode_wait_s=0)
    app = create_app(settings)
    with serve(app) as url:
        page = open_viewer(browser, url)
        refused: list[str] = []
        page.on("response", lambda reply: refused.append(reply.url)
                if reply.status == 503 and "/result" in reply.url else None)  # fmt: skip
        job_id = submit(page, frame)  # no worker yet: the job waits in the queue
        slots = app.state.mcam.decode_slots
        assert slots.take()  # another request's preview
        with running_worker(settings):
            wait_for_js(page, "document.getElementById('status').textContent.includes('succeeded')")
            deadline = time.monotonic() + 30
            while not refused and time.monotonic() < deadline:
                page.wait_for_timeout(50)
            assert refused, "no result was refused while the one slot was held"
            yield page, job_id, slots


def test_results_the_server_is_too_busy_to_make_are_asked_for_again(
    browser: Browser, redis_url: str, frame: Path, tmp_path: Path
) -> None:
    """Previews take a turn of MCAM_MAX_CONCURRENT_DECODES and answer 503 server_busy
    past MCAM_DECODE_WAIT_S (here 0): the page asks again after Retry-After, and shows
    the results once a turn comes (it gave up at the first 503)."""
    with previews_refused(browser, redis_url, frame, tmp_path) as (page, job_id, slots):
        slots.release()
        wait_for_panels(page)
        assert page.inner_text("#status") == f"job {job_id}: succeeded"


def test_results_asked_for_again_are_said_to_be(
    browser: Browser, redis_url: str, frame: Path, tmp_path: Path
) -> None:
    """While its previews were refused and asked for again (four Retry-Afters in all:
    minutes on a 429), the page showed 'succeeded' beside empty panels, with no word."""
    with previews_refused(browser, redis_url, frame, tmp_path) as (page, job_id, slots):
        status = wait_for_status(page, "retrying in")
        assert status.startswith(
            f"job {job_id}: succeeded; its results: the server answered server_busy: "
        ), status
        assert page.get_attribute("#status", "class") == "warning"
        slots.release()
        wait_for_panels(page)
        assert page.inner_text("#status") == f"job {job_id}: succeeded"
        assert page.get_attribute("#status", "class") == ""


def test_a_preview_at_another_exposure_asked_for_again_is_said_to_be(
    browser: Browser, redis_url: str, frame: Path, tmp_path: Path
) -> None:
    """The exposure slider's preview refused 503 server_busy was asked for again with
    nothing said: the old exposure stayed on screen for up to four Retry-Afters."""
    with previews_refused(browser, redis_url, frame, tmp_path) as (page, job_id, slots):
        slots.release()
        wait_for_panels(page)
        assert page.inner_text("#status") == f"job {job_id}: succeeded"
        assert slots.take()  # another request's preview again
        before = page.get_attribute("#img-hdr", "src")
        page.fill("#exposure", "-2")
        page.dispatch_event("#exposure", "input")
        status = wait_for_status(page, "retrying in")
        assert status.startswith(f"job {job_id}: succeeded; its results: "), status
        slots.release()
        wait_for_js(page, f"document.getElementById('img-hdr').src !== {before!r}")
        assert page.inner_text("#status") == f"job {job_id}: succeeded"


def test_cancel_after_the_job_finished_stops_fetching_its_results(
    browser: Browser, redis_url: str, frame: Path, tmp_path: Path
) -> None:
    """Cancel pressed while a succeeded job's previews were refused 503 server_busy: the
    server answered 409 (already succeeded) and the page went on asking for them, after
    each Retry-After, with nothing said; now it stops and says why."""
    with previews_refused(browser, redis_url, frame, tmp_path) as (page, job_id, slots):
        results = api_requests(page, "/result")
        page.click("#cancel")
        status = wait_for_status(page, "stopped fetching")
        assert f"job {job_id} already succeeded" in status, status
        slots.release()
        page.wait_for_timeout((BUSY_RETRY_AFTER_S + 1) * 1000)
        assert results == []
        assert panels_empty(page) and page.is_enabled("#run") and page.is_disabled("#cancel")


def test_cancel_after_the_job_failed_shows_why_it_failed(
    browser: Browser, api: str, settings: Settings, tmp_path: Path
) -> None:
    """Cancel pressed before the page saw its job fail: the server answered 409 (already
    failed) and the page said it had 'stopped fetching its results', which a failed job
    has none of, and never showed why the job failed. It now shows the job's record."""
    overflow = tmp_path / "overflow.npy"
    overflow.write_bytes(npy_bytes(overflowing_codes(SIZE)))
    page = open_viewer(browser, api, fake_clock=True)
    page.select_option("#encoding", "mantissa")
    page.fill("#alpha", "1e6")
    page.fill("#bits", "8")
    job_id = submit(page, overflow)  # no worker yet: the job stays queued
    page.clock.pause_at(page.evaluate("Date.now()") + 1)  # no poll after the first
    wait_for_status(page, f"job {job_id}: queued")
    headers = {"Authorization": f"Bearer {FULL_KEY}"}
    with running_worker(settings):
        deadline = time.monotonic() + 30
        while httpx.get(f"{api}/v1/jobs/{job_id}", headers=headers).json()["state"] != "failed":
            assert time.monotonic() < deadline, "the worker did not fail the job"
            time.sleep(0.1)
    assert page.inner_text("#status") == f"job {job_id}: queued"
    page.click("#cancel")
    status = wait_for_status(page, "output_overflow")
    assert status.startswith(f"job {job_id}: failed"), status
    assert page.is_enabled("#run") and page.is_disabled("#cancel")


def test_a_rate_limited_poll_waits_as_retry_after_says(
    browser: Browser, redis_url: str, frame: Path, tmp_path: Path
) -> None:
    settings = make_settings(tmp_path, redis_url, rate_limit_per_minute=6)
    with serve(create_app(settings)) as url:
        page = open_viewer(browser, url)  # GET /v1/decoders: 1 of 6
        polls = api_requests(page, "/v1/")
        job_id = submit(page, frame)  # POST: 2 of 6; the 7th request is refused
        status = wait_for_status(page, "rate_limited")
        assert job_id in status and page.get_attribute("#status", "class") == "warning"
        waiting = re.search(r"retrying in (\d+) s", status)
        assert waiting is not None and int(waiting.group(1)) >= 30, status
        refused = len(polls)
        page.wait_for_timeout(2_000)
        assert len(polls) == refused, "the page polled again before Retry-After"
        assert page.is_enabled("#cancel")


def hold_first(page: Page, url: str) -> list[Route]:
    """Leave the page's first request to ``url`` (a glob) unanswered, as on a connection
    that died without closing; the held request is appended to the list returned."""
    held: list[Route] = []

    def hold_once(route: Route) -> None:
        if held:
            route.continue_()
        else:
            held.append(route)  # never answered

    page.route(url, hold_once)
    return held


def wait_for_held(page: Page, held: list[Route]) -> None:
    """Wait until :func:`hold_first` holds a request."""
    deadline = time.monotonic() + 30
    while not held:
        assert time.monotonic() < deadline, "the page did not make the request"
        page.wait_for_timeout(POLL_MS)


def test_a_poll_left_unanswered_is_given_up_and_asked_again(
    browser: Browser, api: str, frame: Path
) -> None:
    """A poll whose answer never came (a connection that died without closing, as on a
    network that changed) was waited for without end: the status read "queued" however
    long, and no poll went out again."""
    page = open_viewer(browser, api, fake_clock=True)
    job_id = submit(page, frame)  # no worker: the job stays queued
    held = hold_first(page, f"**/v1/jobs/{job_id}")
    page.clock.run_for(1_000)
    wait_for_held(page, held)
    # Past the poll's 20 s time-out but not its first retry (1 s later): run further,
    # the retry's answer could replace the status before it was read.
    page.clock.run_for(20_500)
    status = wait_for_status(page, "connection to the server lost")
    assert job_id in status and "retrying in" in status
    page.clock.run_for(10_000)
    assert wait_for_status(page, "queued") == f"job {job_id}: queued"


def test_a_result_left_unanswered_is_given_up_and_can_be_fetched_again(
    browser: Browser, api: str, worker: Worker, frame: Path
) -> None:
    """A result whose answer never came after the job succeeded (a connection that died
    without closing) was waited for without end: the panels stood empty beside
    "succeeded" until Cancel. It is given up with what failed, and a reload (the address
    names the job) fetches the results without running the job again."""
    page = open_viewer(browser, api, fake_clock=True)
    held = hold_first(page, "**/result?part=winding&format=png")
    job_id = submit(page, frame)
    wait_for_held(page, held)
    page.clock.run_for(60_500)  # past the result's 60 s time-out
    status = wait_for_status(page, "could not be fetched")
    assert status.startswith(f"job {job_id} succeeded, but its results could not be "
                             "fetched (no answer from the server within 60 s"), status
    assert status.endswith(f"reload the page (its address names job {job_id}) to fetch "
                           "them again"), status
    assert page.get_attribute("#status", "class") == "error"
    assert page.is_enabled("#run") and page.is_disabled("#cancel")
    jobs = api_requests(page, "/v1/reconstructions")
    page.reload()
    wait_for_panels(page)
    assert page.inner_text("#status") == f"job {job_id}: succeeded"
    assert jobs == []


def test_an_upload_can_be_cancelled(browser: Browser, api: str, frame: Path) -> None:
    """Cancel was enabled only once the server had answered the upload with the job's
    id: a large file's upload (or one whose connection hung) could not be stopped."""
    page = open_viewer(browser, api)
    held = hold_first(page, "**/v1/reconstructions")
    page.set_input_files("#file", str(frame))
    page.click("#run")
    wait_for_held(page, held)
    assert page.inner_text("#status") == "uploading the frame…"
    assert page.is_enabled("#cancel")
    page.click("#cancel")
    status = wait_for_status(page, "upload cancelled")
    assert status.endswith("press Reconstruct to upload the file again"), status
    assert page.get_attribute("#status", "class") == ""
    assert page.is_enabled("#run") and page.is_disabled("#cancel")
    assert "#job=" not in page.url
    job_id = submit(page, frame)  # the next upload goes through
    assert wait_for_status(page, "queued") == f"job {job_id}: queued"


class AnswerHeld:
    """ASGI middleware holding the answer to the first ``POST path`` (its job queued, the
    browser told nothing) until ``release`` is set; ``answered`` is set once it is ready."""

    def __init__(self, app: ASGIApp, path: str, answered: threading.Event,
                 release: threading.Event) -> None:
        self.app, self.path, self.answered, self.release = app, path, answered, release

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if (scope["type"] != "http" or scope["method"] != "POST" or scope["path"] != self.path
                or self.release.is_set()):
            return await self.app(scope, receive, send)

        async def held(message: Message) -> None:
            if message["type"] == "http.response.start":
                self.answered.set()
                await anyio.to_thread.run_sync(self.release.wait)
            await send(message)

        return await self.app(scope, receive, held)


@contextmanager
def answer_held(
    browser: Browser, settings: Settings, frame: Path
) -> Iterator[tuple[Page, str, threading.Event]]:
    """The viewer on a server that holds back its answer to the page's first upload (the
    job queued): yields the page, pressed Reconstruct and waiting for that answer, the
    upload's Idempotency-Key and the event that lets such answers go."""
    answered, release = threading.Event(), threading.Event()
    app = create_app(settings)
    app.add_middleware(AnswerHeld, path="/v1/reconstructions", answered=answered,
                       release=release)
    with serve(app) as url:
        try:
            page = open_viewer(browser, url)
            page.set_input_files("#file", str(frame))
            with page.expect_request("**/v1/reconstructions") as upload:
                page.click("#run")
            assert answered.wait(30), "the server did not queue the job"
            yield page, upload.value.headers["idempotency-key"], release
        finally:
            release.set()


def job_by_key(page: Page, key: str) -> dict:
    """The job the upload with Idempotency-Key ``key`` made, as the API shows it."""
    url = page.url.split("#")[0].rstrip("/")
    reply = httpx.get(f"{url}/v1/jobs", params={"idempotency_key": key},
                      headers={"Authorization": f"Bearer {FULL_KEY}"})
    assert reply.status_code == 200, reply.text
    return dict(reply.json())


def test_a_cancel_after_the_server_made_the_job_cancels_it(
    browser: Browser, tmp_path: Path, redis_url: str, frame: Path
) -> None:
    """Cancel pressed after the server had received the whole upload and queued its job,
    before its answer reached the page: the job ran on, followed by no page. The page
    finds it by its upload's Idempotency-Key (asked again while the server said it was
    still handling the upload) and cancels it. The server holds its answer here, so the
    race is always lost the same way."""
    settings = make_settings(tmp_path, redis_url)
    with answer_held(browser, settings, frame) as (page, key, release):
        lookups: list[str] = []

        def in_use_first(route: Route) -> None:
            lookups.append(route.request.url)
            if len(lookups) > 1:
                return route.continue_()
            return route.fulfill(status=409, headers={"Retry-After": "1"}, json={
                "code": "idempotency_key_in_use", "message": "still being decoded"})

        page.route(re.compile(r"/v1/jobs\?idempotency_key="), in_use_first)
        page.click("#cancel")
        status = wait_for_status(page, "cancelled")
        job = job_by_key(page, key)
        assert status == f"job {job['id']}: cancelled" and job["state"] == "cancelled"
        assert len(lookups) == 2
        assert page.get_attribute("#status", "class") == ""
        assert page.is_enabled("#run") and page.is_disabled("#cancel")
        assert page.url.endswith(f"#job={job['id']}")
        assert connect(redis_url).xlen(JOBS_STREAM) == 1  # that job alone was made
        release.set()
        with page.expect_request("**/v1/reconstructions") as upload:
            page.click("#run")
        assert upload.value.headers["idempotency-key"] != key  # a key per upload
        wait_for_status(page, "queued")


def test_a_cancel_whose_lookup_fails_says_how_to_find_the_job(
    browser: Browser, tmp_path: Path, redis_url: str, frame: Path
) -> None:
    """The server could not say whether the cancelled upload made a job: the page said
    the job, if any, ran on, but not how to find it. It names the lookup with the
    upload's Idempotency-Key."""
    settings = make_settings(tmp_path, redis_url)
    with answer_held(browser, settings, frame) as (page, key, _):
        page.route(re.compile(r"/v1/jobs\?idempotency_key="), lambda route: route.fulfill(
            status=403, json={"code": "forbidden", "message": "no submit scope"}))
        page.click("#cancel")
        status = wait_for_status(page, "could not say whether it made a job")
        assert f"GET /v1/jobs?idempotency_key={key} finds it" in status, status
        assert page.get_attribute("#status", "class") == "error"


def test_a_cancel_after_the_upload_s_job_finished_says_so(
    browser: Browser, tmp_path: Path, redis_url: str, frame: Path
) -> None:
    """The job of an upload whose answer had not come yet succeeded before Cancel: the
    page says so, as for a job it followed."""
    settings = make_settings(tmp_path, redis_url)
    with answer_held(browser, settings, frame) as (page, key, _), running_worker(settings):
        deadline = time.monotonic() + 60
        while job_by_key(page, key)["state"] != "succeeded":
            assert time.monotonic() < deadline, "the job did not succeed"
            page.wait_for_timeout(POLL_MS)
        page.click("#cancel")
        status = wait_for_status(page, "had finished before Cancel")
        job_id = job_by_key(page, key)["id"]
        assert status.startswith(f"job {job_id} had finished before Cancel"), status
        assert page.is_enabled("#run") and page.is_disabled("#cancel")


def test_a_cancel_left_unanswered_stops_the_wait_and_says_so(
    browser: Browser, api: str, frame: Path
) -> None:
    """Cancel on a connection that died without closing did nothing: its DELETE was
    waited for without end, and the page went on waiting for the job."""
    page = open_viewer(browser, api, fake_clock=True)
    job_id = submit(page, frame)  # no worker: the job stays queued
    wait_for_status(page, f"job {job_id}: queued")
    held: list[Route] = []
    page.route(f"**/v1/jobs/{job_id}", lambda route: held.append(route)
               if route.request.method == "DELETE" else route.continue_())  # fmt: skip
    page.click("#cancel")
    wait_for_held(page, held)
    page.clock.run_for(20_500)  # past the request's 20 s time-out
    status = wait_for_status(page, "could not cancel")
    assert status.startswith(f"job {job_id}: stopped waiting, but the server could not "
                             "cancel it (no answer from the server within 20 s"), status
    assert status.endswith("reload the page (its address names it) to follow it again")
    assert page.is_enabled("#run") and page.is_disabled("#cancel")
    assert page.url.endswith(f"#job={job_id}")


def test_lists_left_unanswered_are_given_up_and_say_how_to_ask_again(
    browser: Browser, api: str, settings: Settings
) -> None:
    """The decoder and device lists whose answer never came (a connection that died
    without closing) were waited for without end: the choices stood empty, no word said."""
    assert settings.redis_url is not None
    register_device(settings.redis_url, "cam1")
    page = browser.new_page()
    page.clock.install()
    decoders = hold_first(page, "**/v1/decoders")
    devices = hold_first(page, "**/v1/devices")
    page.goto(f"{api}/")
    page.fill("#api-key", FULL_KEY)
    page.click("#key-form button")
    wait_for_held(page, decoders)
    page.click("#live-refresh")
    wait_for_held(page, devices)
    page.clock.run_for(20_500)  # past the requests' 20 s time-out
    status = wait_for_status(page, "cannot list decoders")
    assert "no answer from the server within 20 s" in status, status
    assert "press Save key to list them again" in status, status
    live = wait_for_js(
        page,
        "(() => { const line = document.getElementById('live-status').textContent;"
        " return line.startsWith('cannot list devices') ? line : null; })()",
    )
    assert live.startswith("cannot list devices: no answer from the server within 20 s"), live
    assert live.endswith("; press List devices to try again"), live
    page.click("#key-form button")
    page.wait_for_selector("#decoder option[value=itoh]", state="attached")
    page.click("#live-refresh")
    page.wait_for_selector("#live-device option[value=cam1]", state="attached")


def test_the_job_s_status_is_said_again_only_when_it_changed(
    browser: Browser, api: str, frame: Path
) -> None:
    """The job's status is a live region, and each poll wrote it again with the same
    text ("job …: queued"): a screen reader read it out again at every poll."""
    page = open_viewer(browser, api)
    polls = api_requests(page, "/v1/jobs/")
    job_id = submit(page, frame)  # no worker: the job stays queued
    wait_for_status(page, f"job {job_id}: queued")
    page.evaluate(
        "window.said = []; new MutationObserver((records) => { for (const record of records)"
        " window.said.push(record.target.textContent); })"
        ".observe(document.getElementById('status'),"
        " { subtree: true, childList: true, characterData: true })"
    )
    polled, deadline = len(polls), time.monotonic() + 30
    while len(polls) < polled + 3:  # two more polls answered "queued"
        assert time.monotonic() < deadline, "the page stopped polling the job"
        page.wait_for_timeout(POLL_MS)
    assert page.evaluate("window.said") == []
    assert page.inner_text("#status") == f"job {job_id}: queued"
    page.click("#cancel")
    assert wait_for_status(page, "cancelled") == f"job {job_id}: cancelled"


def test_reconstruct_and_cancel_pressed_from_the_keyboard_keep_the_focus(
    browser: Browser, api: str, frame: Path
) -> None:
    """Reconstruct and Cancel are disabled once pressed: pressed from the keyboard, they
    dropped the focus to the page's body, and a screen reader lost its place. It goes to
    the job's status, which says what happens next."""
    page = open_viewer(browser, api)
    page.set_input_files("#file", str(frame))
    page.focus("#run")
    page.keyboard.press("Enter")
    wait_for_status(page, "queued")  # no worker: the job waits in the queue
    assert page.evaluate("document.activeElement.id") == "status"
    page.focus("#cancel")
    page.keyboard.press("Enter")
    wait_for_status(page, "cancelled")
    assert page.evaluate("document.activeElement.id") == "status"


def test_a_job_gone_from_the_server_is_given_up_with_a_clear_message(
    browser: Browser, api: str, settings: Settings, frame: Path
) -> None:
    page = open_viewer(browser, api)
    job_id = submit(page, frame)
    wait_for_status(page, "queued")
    assert settings.redis_url is not None
    connect(settings.redis_url).delete(job_key(job_id))  # as when its record expires
    wait_for_js(page, "!document.getElementById('run').disabled")
    status = page.inner_text("#status")
    assert status.startswith(f"job {job_id} no longer exists on the server"), status
    assert "submit the frame again" in status
    assert page.get_attribute("#status", "class") == "error"
    assert page.is_disabled("#cancel")


def register_device(redis_url: str, device: str) -> None:
    """A device whose daemon registered it and went quiet a minute ago (so it may be
    forgotten): in the device set, with its last health."""
    client = connect(redis_url)
    client.sadd(DEVICES_SET, device)
    minute_ago = time.time_ns() - 60 * 10**9
    health = {"state": "connected", "updated_ns": minute_ago, "frames_ok": 0, "fps": 0.0}
    client.hset(health_key(device), mapping={**health, "sequence_gaps": 0, "reconnects": 0})


def store_latest_frame(settings: Settings, device: str) -> None:
    """A SIZE x SIZE reconstruction stored as the device's newest frame, as the worker
    stores one."""
    assert settings.redis_url is not None
    params = SensorParams(encoding="modulo", bits=8, gain=1.0)
    codes = simulate(np.linspace(0, 3, SIZE * SIZE).reshape(SIZE, SIZE), params).codes
    decoded = get_decoder("itoh").decode(codes, params)
    key = f"devices/{device}/000000000001-1-0.exr"
    store = ResultStore(settings.data_dir / RESULTS_DIR, settings.result_retention_s)
    store.write(key, encode_exr_result(codes, decoded.winding, params, decoded.info, {}))
    connect(settings.redis_url).set(latest_key(device), key)


def watch_device(page: Page, device: str) -> list[str]:
    """List the devices, pick ``device``; the device requests the page makes from then."""
    page.click("#live-refresh")
    page.wait_for_selector(f"#live-device option[value={device}]", state="attached")
    polls = api_requests(page, f"/v1/devices/{device}")
    page.select_option("#live-device", device)
    return polls


def test_the_live_view_waits_out_a_rate_limit(
    browser: Browser, redis_url: str, tmp_path: Path
) -> None:
    settings = make_settings(tmp_path, redis_url, rate_limit_per_minute=5)
    register_device(redis_url, "cam1")
    with serve(create_app(settings)) as url:
        page = open_viewer(browser, url)  # GET /v1/decoders: 1 of 5
        polls = watch_device(page, "cam1")  # the list: 2; polls 3 to 5; the 6th is refused
        wait_for_js(
            page, "document.getElementById('live-status').textContent.includes('rate_limited')"
        )
        status = page.inner_text("#live-status")
        assert status.startswith("device cam1: ") and "retrying in" in status, status
        refused = len(polls)
        page.wait_for_timeout(2_500)
        assert len(polls) == refused, "the live view polled again before Retry-After"


def test_the_live_view_stops_watching_a_forgotten_device(
    browser: Browser, api: str, settings: Settings
) -> None:
    assert settings.redis_url is not None
    register_device(settings.redis_url, "cam1")
    page = open_viewer(browser, api)
    polls = watch_device(page, "cam1")
    wait_for_js(page, "document.getElementById('live-status').textContent.includes('silent')")
    headers = {"Authorization": f"Bearer {FULL_KEY}"}
    assert httpx.delete(f"{api}/v1/devices/cam1", headers=headers).status_code == 200
    wait_for_js(
        page,
        "document.getElementById('live-status').textContent.includes('no longer known')"
    )
    assert "press List devices" in page.inner_text("#live-status")
    stopped = len(polls)
    page.wait_for_timeout(2_500)
    assert len(polls) == stopped, "the live view kept polling a device the server forgot"


def test_a_live_poll_left_unanswered_is_given_up_and_asked_again(
    browser: Browser, api: str, settings: Settings
) -> None:
    """A device poll whose answer never came (a connection that died without closing) was
    waited for without end: the live view stood still, however the device came back."""
    assert settings.redis_url is not None
    register_device(settings.redis_url, "cam1")
    page = open_viewer(browser, api, fake_clock=True)
    held = hold_first(page, "**/v1/devices/cam1")
    watch_device(page, "cam1")
    wait_for_held(page, held)
    page.clock.run_for(20_500)  # past the poll's 20 s time-out, not its 1 s retry
    status = wait_for_js(
        page,
        "(() => { const status = document.getElementById('live-status').textContent;"
        " return status.includes('connection to the server lost') ? status : null; })()",
    )
    assert status.startswith("device cam1: ") and "retrying in" in status, status
    page.clock.run_for(2_000)
    wait_for_js(page, "document.getElementById('live-status').textContent.includes('silent')")


def test_the_live_status_is_said_again_only_when_more_than_its_counters_changed(
    browser: Browser, api: str, settings: Settings
) -> None:
    """The live status line is a live region, and it was written at every poll (once a
    second) with the same text, or with only its counters or a silent daemon's age
    changed: a screen reader read it out again every second. Only its said parts are
    announced now, and only when their text changed; the line reads as before."""
    assert settings.redis_url is not None
    register_device(settings.redis_url, "cam1")
    page = open_viewer(browser, api)
    polls = watch_device(page, "cam1")
    first = wait_for_js(
        page,
        "(() => { const line = document.getElementById('live-status').textContent;"
        " return line.includes('silent') ? line : null; })()",
    )
    page.evaluate(  # changes within a live region (its nearest, if nested) are said
        "window.said = []; new MutationObserver((records) => { for (const record of records) {"
        " const node = record.target.nodeType === 1 ? record.target : record.target.parentNode;"
        " const live = node.closest('[aria-live], [role=status], [role=alert], [role=log]');"
        " if (live && live.getAttribute('aria-live') !== 'off')"
        " window.said.push(node.textContent); } })"
        ".observe(document.getElementById('live-status'),"
        " { subtree: true, childList: true, characterData: true })"
    )
    client = connect(settings.redis_url)
    for frames in (1, 2, 3):  # each poll reads other counters and another age
        client.hset(health_key("cam1"), "frames_ok", frames)
        wait_for_js(page, f"document.getElementById('live-status').textContent"
                          f".includes('{frames} frames')")
        polled, deadline = len(polls), time.monotonic() + 30
        while len(polls) < polled + 2:  # and a poll whose counters did not change
            assert time.monotonic() < deadline, "the live view stopped polling"
            page.wait_for_timeout(POLL_MS)
    assert page.evaluate("window.said") == []
    line = page.inner_text("#live-status")
    assert re.fullmatch(r"silent: 3 frames, 0 fps, 0 dropped, 0 gaps, 0 reconnects; its "
                        r"daemon has not reported for \d+ s \(stopped, killed, or cut off "
                        r"from Redis\): check that mcam device runs", line), (first, line)


def test_the_live_view_stopped_by_a_refused_key_resumes_once_a_key_is_saved(
    browser: Browser, api: str, settings: Settings
) -> None:
    """A key refused 401 stopped the watch with "press Save key"; saving the right key
    left it stopped, and choosing the same device again is no change of the choice."""
    assert settings.redis_url is not None
    register_device(settings.redis_url, "cam1")
    page = open_viewer(browser, api)
    watch_device(page, "cam1")
    wait_for_js(page, "document.getElementById('live-status').textContent.includes('silent')")
    page.evaluate("localStorage.setItem('mcam-api-key', 'not-a-key')")  # as another tab
    wait_for_js(
        page, "document.getElementById('live-status').textContent.includes('watch stopped')"
    )
    assert "press Save key" in page.inner_text("#live-status")
    page.click("#key-form button")  # the field still holds the right key
    wait_for_js(page, "document.getElementById('live-status').textContent.includes('silent')")


def test_the_watched_device_is_watched_again_after_a_reload(
    browser: Browser, api: str, settings: Settings
) -> None:
    """A reload forgot the device watched: the live view stood empty until the devices
    were listed and the device chosen again."""
    assert settings.redis_url is not None
    for device in ("cam1", "cam2"):
        register_device(settings.redis_url, device)
    page = open_viewer(browser, api)
    watch_device(page, "cam2")
    wait_for_js(page, "document.getElementById('live-status').textContent.includes('silent')")
    page.reload()
    wait_for_js(page, "document.getElementById('live-status').textContent.includes('silent')")
    assert page.input_value("#live-device") == "cam2"
    page.select_option("#live-device", "")  # none chosen: none to watch after a reload
    assert page.evaluate("sessionStorage.getItem('mcam-live-device')") is None


def test_a_device_list_refused_for_the_key_is_listed_once_a_key_is_saved(
    browser: Browser, api: str, settings: Settings
) -> None:
    """List devices refused 401 said to press Save key; saving the right key left the list
    empty until List devices was pressed again."""
    assert settings.redis_url is not None
    register_device(settings.redis_url, "cam1")
    page = open_viewer(browser, api)
    page.evaluate("localStorage.setItem('mcam-api-key', 'not-a-key')")  # as another tab
    page.click("#live-refresh")
    wait_for_js(
        page, "document.getElementById('live-status').textContent.includes('unknown API key')"
    )
    assert "press Save key" in page.inner_text("#live-status")
    page.click("#key-form button")  # the field still holds the right key
    page.wait_for_selector("#live-device option[value=cam1]", state="attached")


def test_a_key_that_cannot_read_jobs_ends_the_wait_with_the_reason(
    browser: Browser, api: str, frame: Path
) -> None:
    """A submit-only key: the job is queued, then every poll answers 403. That is said
    at once, in red, and the page is ready again (it used to retry every 8 s for good)."""
    page = open_viewer(browser, api)
    page.evaluate(f"localStorage.setItem('mcam-api-key', {SUBMIT_KEY!r})")
    job_id = submit(page, frame)
    wait_for_js(page, "!document.getElementById('run').disabled")
    status = page.inner_text("#status")
    assert status.startswith(f"job {job_id}: ") and "read" in status, status
    assert page.get_attribute("#status", "class") == "error"
    assert page.is_disabled("#cancel")


def test_a_missing_or_unknown_key_says_where_to_enter_it(
    browser: Browser, api: str, frame: Path
) -> None:
    """Reconstruct pressed with no key saved, or with a key the server does not know, told
    the API's 401 only: how to send an HTTP header ("send the header 'Authorization:
    Bearer <key>'") or to look in the data dir, never where on the page the key goes."""
    page = browser.new_page()
    page.goto(f"{api}/")
    uploads = api_requests(page, "/v1/reconstructions")
    page.set_input_files("#file", str(frame))
    page.click("#run")
    status = wait_for_status(page, "no API key saved")
    assert "under API key at the top and press Save key" in status, status
    assert page.get_attribute("#status", "class") == "error"
    assert uploads == []
    page.fill("#api-key", "not-a-key")
    page.click("#key-form button")
    status = wait_for_status(page, "cannot list decoders")
    assert "unknown API key" in status and status.endswith("press Save key"), status
    wait_for_js(page, "!document.getElementById('run').disabled")
    page.click("#run")
    status = wait_for_js(
        page,
        "(() => { const status = document.getElementById('status').textContent;"
        " return status.startsWith('unauthorized: unknown API key') ? status : null; })()",
    )
    assert status.endswith("under API key at the top and press Save key"), status


def test_a_key_with_a_character_no_key_has_is_not_saved(browser: Browser, api: str) -> None:
    """A key pasted with a zero-width space: refused with the reason on Save (fetch
    refused the header, which read as 'cannot reach the server')."""
    page = open_viewer(browser, api)
    page.fill("#api-key", FULL_KEY + "\u200b")
    page.click("#key-form button")
    assert page.inner_text("#status").startswith("not saved: an API key is letters")
    assert page.evaluate("localStorage.getItem('mcam-api-key')") == FULL_KEY


def test_an_exposure_refresh_without_a_shown_job_asks_for_nothing(
    browser: Browser, api: str
) -> None:
    """A slider refresh still pending when a new submit cleared the panels asked for
    job null's preview and put its 404 over the submit's own error."""
    page = open_viewer(browser, api)
    requests = api_requests(page, "/v1/jobs/")
    page.evaluate("refreshHdr()")
    page.wait_for_timeout(300)
    assert requests == []
    assert page.get_attribute("#status", "class") != "error"


def test_a_busy_preview_of_a_job_no_longer_shown_is_not_asked_for_again(
    browser: Browser, redis_url: str, frame: Path, tmp_path: Path
) -> None:
    """A preview refused 503 server_busy was asked for again after each Retry-After (five
    times in all, about 20 s) even once the panels were cleared for another job (a new
    Run clears them): its retries now stop with it."""
    settings = make_settings(tmp_path, redis_url, max_concurrent_decodes=1, decode_wait_s=0)
    app = create_app(settings)
    with serve(app) as url, running_worker(settings):
        done = httpx.post(f"{url}/v1/reconstructions", files={"file": frame.read_bytes()},
                          headers={"Authorization": f"Bearer {FULL_KEY}",
                                   "Prefer": "wait=30"}, timeout=60)
        assert done.json()["state"] == "succeeded", done.text
        page = open_viewer(browser, url, fake_clock=True)
        requests = api_requests(page, "/result")
        assert app.state.mcam.decode_slots.take()  # another request's preview: 503s
        page.evaluate(f"shownJob = {done.json()['id']!r}; refreshHdr(); clearResult()")
        for _ in range(30):  # past five Retry-Afters of the page's clock, each reply in
            page.clock.run_for(1_000)
            page.wait_for_timeout(100)
        assert len(requests) <= 1, requests


def test_another_device_is_not_shown_with_the_previous_ones_frame(
    browser: Browser, api: str, settings: Settings
) -> None:
    """Picking a device that has no frame yet left the previous device's frame on screen,
    captioned as the newest reconstruction, beside the new device's health."""
    assert settings.redis_url is not None
    for device in ("cam1", "cam2"):
        register_device(settings.redis_url, device)
    store_latest_frame(settings, "cam1")
    page = open_viewer(browser, api)
    watch_device(page, "cam1")
    wait_for_js(page, f"document.getElementById('live-frame').naturalWidth === {SIZE}")
    page.select_option("#live-device", "cam2")
    wait_for_js(page, "document.getElementById('live-status').textContent.includes('silent')")
    assert page.get_attribute("#live-frame", "src") is None


def test_no_health_is_shown_once_no_device_is_chosen(
    browser: Browser, api: str, settings: Settings
) -> None:
    """Choosing '(choose a device)' stopped the watch but left the last device's health
    on screen, as if it were still watched."""
    assert settings.redis_url is not None
    register_device(settings.redis_url, "cam1")
    page = open_viewer(browser, api)
    watch_device(page, "cam1")
    wait_for_js(page, "document.getElementById('live-status').textContent.includes('silent')")
    page.select_option("#live-device", "")
    assert page.inner_text("#live-status") == ""


def test_a_device_without_a_health_report_reads_so(browser: Browser, api: str,
                                                   settings: Settings) -> None:
    """A device registered (by its daemon's first frame) before its daemon's first health
    report: the list read 'cam1 (undefined)' and the live status 'undefined: undefined
    frames, undefined fps, 0 dropped, undefined gaps, undefined reconnects'."""
    assert settings.redis_url is not None
    connect(settings.redis_url).sadd(DEVICES_SET, "cam1")
    page = open_viewer(browser, api)
    watch_device(page, "cam1")
    wait_for_js(page, "document.getElementById('live-status').textContent.includes('report')")
    assert page.inner_text("#live-status") == "no health report yet from the device's daemon"
    option = page.inner_text("#live-device option[value=cam1]")
    assert option == "cam1 (no health report yet)"


def test_a_device_whose_port_does_not_open_says_why(browser: Browser, api: str,
                                                    settings: Settings) -> None:
    """The daemon reports why the port does not open (``port_error``: a wrong --port, an
    unplugged camera, another daemon holding it) and what to do; the live view showed
    only 'connecting: 0 frames, ...', with the reason in the daemon's log alone."""
    assert settings.redis_url is not None
    reason = "/dev/ttyUSB7 does not exist: check --port, or plug the camera in"
    register_device(settings.redis_url, "cam1")
    fresh = time.time_ns() + 60 * 10**9  # not shown silent, however slow the test runs
    connect(settings.redis_url).hset(health_key("cam1"), mapping={
        "state": "connecting", "updated_ns": fresh, "port_error": reason,
    })  # fmt: skip
    page = open_viewer(browser, api)
    watch_device(page, "cam1")
    wait_for_js(page, "document.getElementById('live-status').textContent.includes('frames')")
    status = page.inner_text("#live-status")
    assert status.startswith("connecting: 0 frames") and status.endswith(
        f"; its port does not open: {reason}"), status


def test_a_device_whose_daemon_crashed_says_on_what_and_what_to_do(
        browser: Browser, api: str, settings: Settings) -> None:
    """A daemon that stopped on an unexpected error a minute ago: its health read
    'connected' for good (or 'silent', with "check that mcam device runs"). It reads
    'crashed' with the error, and what to do."""
    assert settings.redis_url is not None
    register_device(settings.redis_url, "cam1")
    connect(settings.redis_url).hset(health_key("cam1"), mapping={
        "state": "crashed", "crash": "RuntimeError: not a client mistake", "fps": "0.000",
    })  # fmt: skip
    page = open_viewer(browser, api)
    watch_device(page, "cam1")
    wait_for_js(page, "document.getElementById('live-status').textContent.includes('frames')")
    assert page.inner_text("#live-status") == (
        "crashed: 0 frames, 0 fps, 0 dropped, 0 gaps, 0 reconnects; its daemon stopped on an "
        "unexpected error (RuntimeError: not a client mistake): restart mcam device, and "
        "report the error with the traceback in its log")


def test_a_download_is_named_after_its_job_when_a_run_starts_meanwhile(
    browser: Browser, api: str, worker: Worker, frame: Path
) -> None:
    """Run pressed while the EXR downloads clears the shown job: the file was then saved
    as null.exr."""
    page = open_viewer(browser, api)
    job_id = submit(page, frame)
    wait_for_panels(page)
    held: list[Route] = []
    page.route("**/result?part=image&format=exr", lambda route: held.append(route))
    page.click("#download")
    deadline = time.monotonic() + 30
    while not held:
        assert time.monotonic() < deadline, "the page did not ask for the EXR"
        page.wait_for_timeout(POLL_MS)
    page.evaluate("clearResult()")  # as Run does first
    with page.expect_download() as download:
        held[0].continue_()
    assert download.value.suggested_filename == f"{job_id}.exr"


def test_a_download_that_failed_says_it_was_the_download(
    browser: Browser, api: str, worker: Worker, frame: Path
) -> None:
    """A download that could not reach the server replaced "succeeded" with the bare
    "cannot reach the server", which read as if the job had failed; one whose result is
    gone says to run the job again."""
    page = open_viewer(browser, api)
    job_id = submit(page, frame)
    wait_for_panels(page)
    page.route("**/result?part=image&format=exr", lambda route: route.abort())
    page.click("#download")
    status = wait_for_status(page, "cannot download")
    assert status.startswith(f"cannot download the EXR of job {job_id}: cannot reach"), status
    assert status.endswith("press Download EXR to try again"), status
    assert page.get_attribute("#status", "class") == "error"
    exr = "**/result?part=image&format=exr"
    page.unroute(exr)
    gone = {"code": "gone", "message": "the result has expired"}
    page.route(exr, lambda route: route.fulfill(status=410, json=gone))
    page.click("#download")
    status = wait_for_status(page, "expired")
    assert status.endswith("press Reconstruct to run it again"), status


def test_a_download_the_server_is_too_busy_to_give_is_said_to_be_asked_again(
    browser: Browser, api: str, worker: Worker, frame: Path
) -> None:
    """A download refused 429 was asked for again after each Retry-After without a word:
    the click did nothing to be seen for minutes."""
    page = open_viewer(browser, api)
    job_id = submit(page, frame)
    wait_for_panels(page)
    limited = {"code": "rate_limited", "message": "too many requests"}
    page.route(
        "**/result?part=image&format=exr",
        lambda route: route.fulfill(status=429, json=limited, headers={"Retry-After": "30"}),
    )
    page.click("#download")
    status = wait_for_status(page, "rate_limited")
    assert status.startswith(f"job {job_id}: succeeded; its results: "), status
    assert status.endswith("retrying in 30 s"), status


def test_a_device_whose_daemon_went_silent_says_what_to_check(
    browser: Browser, api: str, settings: Settings
) -> None:
    """A daemon killed (or cut off from Redis) a minute ago: the live view read 'silent:
    0 frames, 0 fps, ...', with neither since when nor what to do."""
    assert settings.redis_url is not None
    register_device(settings.redis_url, "cam1")
    page = open_viewer(browser, api)
    watch_device(page, "cam1")
    wait_for_js(page, "document.getElementById('live-status').textContent.includes('silent')")
    status = page.inner_text("#live-status")
    silent_for = re.search(r"; its daemon has not reported for (\d+) s \(stopped, killed, "
                           r"or cut off from Redis\): check that mcam device runs$", status)
    assert silent_for is not None and int(silent_for.group(1)) >= 60, status


def test_a_decoder_list_that_failed_says_how_to_list_them_again(
    browser: Browser, api: str
) -> None:
    """The decoders are listed only at load and on Save key: one that failed (the server
    down, a 429) left the choice empty with no word of how to fill it once the server
    answers."""
    page = browser.new_page()
    page.route("**/v1/decoders", lambda route: route.abort())
    page.goto(f"{api}/")
    page.fill("#api-key", FULL_KEY)
    page.click("#key-form button")
    status = wait_for_status(page, "cannot list decoders")
    assert "cannot reach the server" in status and "press Save key to list them again" in status
    page.unroute("**/v1/decoders")
    page.click("#key-form button")
    page.wait_for_selector("#decoder option[value=itoh]", state="attached")
