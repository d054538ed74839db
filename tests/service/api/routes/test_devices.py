"""``/v1/devices``: a virtual camera on a real pty, the real daemon, a real worker, real HTTP
(the event stream's own limits: test_device_events.py)."""

from __future__ import annotations

import io
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pytest
from PIL import Image

from device.simulator import VirtualScamp5
from models.decoders.registry import get_decoder
from models.display import srgb8
from models.formation import SensorParams, simulate
from models.hdr_io import read_hdr
from service.api.routes import devices as device_routes
from service.core.config import Settings
from service.main import create_app
from tests.device.conftest import wait_for
from tests.service.api.conftest import live_camera, stopped_device
from tests.service.conftest import FULL_KEY, READ_KEY, SUBMIT_KEY, make_settings, serve
from tests.service.static.conftest import chromium, needs_chromium, wait_for_js
from worker.control_queue import CONTROL_BACKLOG
from worker.embedded_redis import connect
from worker.outputs import encode_exr_result
from worker.redis_keys import DEVICES_SET, control_stream, health_key, latest_key
from worker.result_store import RESULTS_DIR, ResultStore


@pytest.fixture
def camera(settings: Settings, tmp_path: Path) -> Iterator[VirtualScamp5]:
    """A streaming virtual camera, its daemon and a device-consuming worker."""
    with live_camera(settings, tmp_path, fps=20, seed=1, max_frames=15) as cam:
        yield cam


def test_devices_health_control_latest_and_events(
    camera: VirtualScamp5, client: Callable[[str], httpx.Client]
) -> None:
    http = client(FULL_KEY)
    assert wait_for(lambda: any(d["frames_ok"] >= 5 for d in
                                http.get("/v1/devices").json()["devices"]), 30)
    listing = http.get("/v1/devices").json()["devices"]
    assert [d["id"] for d in listing] == ["cam1"]
    one = http.get("/v1/devices/cam1").json()
    assert one["settings"]["width"] == 256 and one["settings"]["encoding"] == "modulo"
    assert set(one["dropped"]) >= {"bad_crc", "queue_full", "redis_unavailable"}
    assert http.get("/v1/devices/nope").status_code == 404
    assert http.get("/v1/devices/bad!id").json()["code"] == "invalid_input"

    command = {"command": "set_frame_rate", "fps": 50}
    assert client(READ_KEY).post("/v1/devices/cam1/control", json=command).status_code == 403
    assert client("").post("/v1/devices/cam1/control", json=command).status_code == 401
    reply = client(SUBMIT_KEY).post("/v1/devices/cam1/control", json=command)
    assert reply.status_code == 202 and reply.json()["command"]["fps"] == 50
    assert wait_for(lambda: camera.settings.fps == 50, 10)
    bad = http.post("/v1/devices/cam1/control", json={"command": "set_frame_rate", "fps": -1})
    assert bad.status_code == 422
    unknown = http.post("/v1/devices/cam1/control", json={"command": "fly"})
    assert unknown.status_code == 422
    assert "field 'command' is one of start, stop" in unknown.json()["message"]
    busy = http.delete("/v1/devices/cam1")
    assert busy.status_code == 409 and busy.json()["code"] == "device_busy", busy.text
    assert "stop it" in busy.json()["message"]

    assert wait_for(lambda: http.get("/v1/devices/cam1/frames/latest").status_code == 200, 60)
    exr = http.get("/v1/devices/cam1/frames/latest")
    assert read_hdr(exr.content).pixels.shape == (256, 256)
    png = http.get("/v1/devices/cam1/frames/latest", params={"format": "png", "exposure": -2})
    assert png.status_code == 200 and png.content.startswith(b"\x89PNG")

    with http.stream("GET", "/v1/devices/cam1/events",
                     params={"since": "0", "limit": 2}) as events:
        assert events.headers["content-type"].startswith("text/event-stream")
        body = "".join(events.iter_text())
    assert body.count("event: frame") == 2 and '"sequence": "0"' in body
    future = {"Last-Event-ID": f"{(time.time_ns() // 10**6) + 10**9}-0"}
    with http.stream("GET", "/v1/devices/cam1/events", params={"limit": 1},
                     headers=future) as events:
        body = "".join(events.iter_text())
    assert body.count("event: reset") == 1 and body.count("event: frame") == 1, body
    assert '"sequence": "0"' in body  # from the oldest kept event
    for huge in ("1-" + "9" * 23, "1-" + "9" * 5000):  # 5000 digits: int() refuses them
        for params, headers in [({"since": huge}, {}), ({}, {"Last-Event-ID": huge})]:
            refused = http.get("/v1/devices/cam1/events", params=params, headers=headers)
            assert refused.status_code == 422, refused.text
            assert "below 2^64" in refused.json()["message"]


def test_a_device_whose_daemon_went_quiet_is_shown_silent_and_can_be_forgotten(
    settings: Settings, client: Callable[..., httpx.Client]
) -> None:
    """A daemon killed outright leaves its last health behind: the API says how old it is
    and stops calling the device connected."""
    assert settings.redis_url is not None
    redis_client = connect(settings.redis_url)
    redis_client.sadd(DEVICES_SET, "gone")
    minute_ago = time.time_ns() - 60 * 10**9
    redis_client.hset(health_key("gone"), mapping={
        "state": "connected", "fps": "10.000", "updated_ns": str(minute_ago),
    })  # fmt: skip
    view = client(READ_KEY).get("/v1/devices/gone").json()
    assert view["state"] == "silent" and view["last_state"] == "connected"
    assert view["fps"] == 0.0 and view["age_s"] >= 60

    head = client(READ_KEY).head("/v1/devices/gone/events", timeout=10)  # a stream: ends
    assert head.status_code == 200 and head.headers["content-type"].startswith("text/event")
    assert client(READ_KEY).delete("/v1/devices/gone").status_code == 403
    forgotten = client(SUBMIT_KEY).delete("/v1/devices/gone")
    assert forgotten.status_code == 200, forgotten.text
    assert forgotten.json() == {"device": "gone", "forgotten": True, "frames_discarded": 0}
    assert client(READ_KEY).get("/v1/devices").json()["devices"] == []
    assert client(SUBMIT_KEY).delete("/v1/devices/gone").status_code == 404


def test_a_device_whose_daemon_stopped_streams_at_0_fps(
    settings: Settings, client: Callable[..., httpx.Client]
) -> None:
    """A daemon's last health write, as it stops, measures the frames that came before
    the stop: its device read 'stopped' at 19.285 fps for good (the web viewer showed
    'stopped: 40 frames, 19.285 fps')."""
    assert settings.redis_url is not None
    redis_client = connect(settings.redis_url)
    redis_client.sadd(DEVICES_SET, "cam1")
    redis_client.hset(health_key("cam1"), mapping={
        "state": "stopped", "fps": "19.285", "frames_ok": "40", "updated_ns": str(time.time_ns()),
    })  # fmt: skip
    view = client(READ_KEY).get("/v1/devices/cam1").json()
    assert view["state"] == "stopped" and view["frames_ok"] == 40
    assert view["fps"] == 0.0


def test_a_device_whose_daemon_crashed_says_on_what_however_long_ago(
    settings: Settings, client: Callable[..., httpx.Client]
) -> None:
    """A daemon that stopped on an unexpected error leaves ``crashed`` and the error as
    its last word: the device is not called silent after 10 s (which hid the error in
    ``last_state``, and said to check that mcam device runs), and streams at 0 fps."""
    assert settings.redis_url is not None
    redis_client = connect(settings.redis_url)
    redis_client.sadd(DEVICES_SET, "cam1")
    minute_ago = time.time_ns() - 60 * 10**9
    redis_client.hset(health_key("cam1"), mapping={
        "state": "crashed", "crash": "RuntimeError: 42", "fps": "19.285",
        "updated_ns": str(minute_ago),
    })  # fmt: skip
    view = client(READ_KEY).get("/v1/devices/cam1").json()
    assert (view["state"], view["crash"], view["fps"]) == ("crashed", "RuntimeError: 42", 0.0)
    assert "last_state" not in view and view["age_s"] >= 60


def test_commands_for_a_stopped_daemon_are_refused_past_the_backlog(
    settings: Settings, client: Callable[..., httpx.Client]
) -> None:
    """Before, every command was accepted (202) and the stream's bound then trimmed the
    oldest ones unread: accepted commands were lost."""
    assert settings.redis_url is not None
    redis_client = connect(settings.redis_url)
    redis_client.sadd(DEVICES_SET, "idle")
    http = client(SUBMIT_KEY)
    command = {"command": "set_frame_rate", "fps": 20}
    accepted = [http.post("/v1/devices/idle/control", json=command) for _ in range(CONTROL_BACKLOG)]
    assert {reply.status_code for reply in accepted} == {202}
    refused = http.post("/v1/devices/idle/control", json=command)
    assert refused.status_code == 503 and refused.headers["retry-after"] == "5"
    assert refused.json()["code"] == "control_backlog_full"
    assert redis_client.xlen(control_stream("idle")) == CONTROL_BACKLOG


def store_latest_frame(settings: Settings, params: SensorParams, size: int) -> bytes:
    """Store a ``size`` x ``size`` ramp decoded as device cam9's newest frame, as its
    worker would; the EXR's bytes."""
    assert settings.redis_url is not None
    codes = simulate(np.linspace(0, 3, size * size).reshape(size, size), params).codes
    decoded = get_decoder("itoh").decode(codes, params)
    exr = encode_exr_result(codes, decoded.winding, params, decoded.info, {})
    key = "devices/cam9/000000000001-1-0.exr"
    ResultStore(settings.data_dir / RESULTS_DIR, settings.result_retention_s).write(key, exr)
    redis_client = connect(settings.redis_url)
    redis_client.sadd(DEVICES_SET, "cam9")
    redis_client.set(latest_key("cam9"), key)
    return exr


def test_the_live_preview_shares_the_job_previews_wrap_units(
    settings: Settings, client: Callable[..., httpx.Client]
) -> None:
    """Device frames are stored scene-referred (x / gain): the PNG preview multiplies the
    gain back, as a job's preview does, so the one exposure slider means the same on
    both (a gain-8 camera looked 3 EV darker live)."""
    exr = store_latest_frame(settings, SensorParams(encoding="modulo", bits=8, gain=8.0), 64)
    png = client(READ_KEY).get("/v1/devices/cam9/frames/latest", params={"format": "png"})
    assert png.status_code == 200, png.text
    shown = np.asarray(Image.open(io.BytesIO(png.content)))
    np.testing.assert_array_equal(shown, srgb8(read_hdr(exr).pixels * 8.0))


def test_an_exposure_for_the_newest_exr_is_refused(
    settings: Settings, client: Callable[..., httpx.Client]
) -> None:
    """``frames/latest?exposure=2`` got the EXR, unchanged, as if the exposure had not
    been given: the client meant the tonemapped preview, which ``format=png`` gives."""
    store_latest_frame(settings, SensorParams(encoding="modulo", bits=8, gain=1.0), 16)
    http, latest = client(READ_KEY), "/v1/devices/cam9/frames/latest"
    for params in ({"exposure": "2"}, {"format": "exr", "exposure": "0"}):
        reply = http.get(latest, params=params)
        assert reply.status_code == 422, (params, reply.text)
        assert "ask for format=png with it" in reply.json()["message"]
    assert http.get(latest, params={"format": "png", "exposure": "2"}).status_code == 200


def test_the_live_preview_is_made_in_turn(tmp_path: Path, redis_url: str) -> None:
    """A device's PNG frame reads and tonemaps the stored EXR in the API's memory, as a
    job's preview does: it takes a turn of MCAM_MAX_CONCURRENT_DECODES (503 server_busy
    with Retry-After past MCAM_DECODE_WAIT_S); the EXR itself is streamed without one."""
    settings = make_settings(tmp_path, redis_url, max_concurrent_decodes=1, decode_wait_s=0)
    store_latest_frame(settings, SensorParams(encoding="modulo", bits=8, gain=1.0), 16)
    app = create_app(settings)
    with serve(app) as url:
        latest = f"{url}/v1/devices/cam9/frames/latest"
        headers = {"Authorization": f"Bearer {READ_KEY}"}
        slots = app.state.mcam.decode_slots
        assert slots.take()
        refused = httpx.get(latest, params={"format": "png"}, headers=headers)
        assert refused.status_code == 503 and refused.json()["code"] == "server_busy"
        assert refused.headers["retry-after"] == "5"
        assert httpx.get(latest, headers=headers).status_code == 200
        slots.release()
        assert httpx.get(latest, params={"format": "png"}, headers=headers).status_code == 200
        assert not slots.full


@pytest.mark.slow
@needs_chromium
def test_web_page_live_view_shows_the_device(camera: VirtualScamp5, api: str) -> None:
    with chromium() as browser:
        page = browser.new_page()
        errors: list[str] = []
        page.on("pageerror", lambda exc: errors.append(str(exc)))
        page.goto(f"{api}/")
        page.fill("#api-key", FULL_KEY)
        page.click("#key-form button")
        wait_for_js(page, "localStorage.getItem('mcam-api-key') !== null")
        page.click("#live-refresh")
        page.wait_for_selector("#live-device option[value=cam1]", state="attached")
        page.select_option("#live-device", "cam1")
        wait_for_js(page, "document.getElementById('live-frame').naturalWidth === 256",
                    timeout_ms=60_000)
        assert "frames" in page.inner_text("#live-status")
    assert errors == []


def test_a_command_racing_the_devices_forget_is_refused_not_lost(
    settings: Settings, client: Callable[..., httpx.Client], monkeypatch: pytest.MonkeyPatch
) -> None:
    """A command and a DELETE of a stopped device at once, the DELETE landing after the
    command's route found the device registered (held there: the order that lost it).
    Before, the command was accepted (202) into a stream of a device already forgotten,
    and a daemon coming back skipped it (its cursor went with the device): accepted and
    lost. It is now refused, 404 like any command for an unknown device."""
    redis_client = stopped_device(settings, "idle")
    http = client(SUBMIT_KEY)
    append = device_routes.queue_command
    forgotten: list[httpx.Response] = []

    def forget_then_append(*args: Any, **kwargs: Any) -> str:
        forgotten.append(client(SUBMIT_KEY).delete("/v1/devices/idle"))
        return append(*args, **kwargs)

    monkeypatch.setattr(device_routes, "queue_command", forget_then_append)
    sent = http.post("/v1/devices/idle/control", json={"command": "set_frame_rate", "fps": 20})
    assert [reply.status_code for reply in forgotten] == [200]
    assert sent.status_code == 404 and sent.json()["code"] == "not_found", sent.text
    assert redis_client.exists(control_stream("idle")) == 0
