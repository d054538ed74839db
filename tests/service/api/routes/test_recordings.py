"""``/v1/devices/{id}/recordings``: a virtual camera on a real pty, the real daemon, a real
worker (device frames and jobs), real HTTP; the recorded video's files read back."""

from __future__ import annotations

import io
import json
import threading
import zipfile
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import av
import httpx
import numpy as np
import pytest
from redis.commands.core import Script

from device.simulator import VirtualScamp5
from models.formation import reconstruct, simulate
from models.hdr_io import read_hdr
from service.api.routes import recordings as recording_routes
from service.core.config import Settings
from service.main import create_app
from tests.device.conftest import wait_for
from tests.service.api.conftest import live_camera, stopped_device
from tests.service.conftest import (
    FULL_KEY,
    PARAMS,
    READ_KEY,
    SUBMIT_KEY,
    finished_job,
    make_settings,
    scene,
    serve,
)
from tests.worker.conftest import leave_free
from worker import recordings
from worker.embedded_redis import connect
from worker.frame_message import FrameMessage
from worker.recorder import Recorder
from worker.redis_keys import DEVICES_SET, health_key, recording_key
from worker.result_store import RESULTS_DIR, ResultStore

Client = Callable[[str], httpx.Client]
FRAMES = 30
URL = "/v1/devices/cam1/recordings"


@pytest.fixture
def camera(settings: Settings, tmp_path: Path) -> Iterator[VirtualScamp5]:
    with live_camera(settings, tmp_path, fps=15, seed=3, history=1000) as cam:
        yield cam


def recording(http: httpx.Client, url: str = URL) -> dict:
    reply = http.get(url)
    assert reply.status_code == 200, reply.text
    return reply.json()


def test_thirty_frame_live_recording_into_hdr10_and_exr(
    camera: VirtualScamp5, client: Client
) -> None:
    http = client(FULL_KEY)
    assert wait_for(lambda: http.get("/v1/devices/cam1").status_code == 200, 30)
    start = {"action": "start", "max_frames": FRAMES, "mode": "temporal", "decoder": "itoh"}
    reply = http.post(URL, json=start)
    assert reply.status_code == 201, reply.text
    assert reply.json()["state"] == "recording" and reply.headers["location"] == URL
    again = http.post(URL, json=start)
    assert again.status_code == 409 and again.json()["code"] == "recording_running"

    assert wait_for(lambda: recording(http)["state"] != "recording", 40)
    done = recording(http)
    assert done["state"] == "submitted" and done["reason"] == "max_frames", done
    assert done["frames"] == FRAMES and done["keyframes"] == []
    assert done["last_sequence"] - done["first_sequence"] == FRAMES - 1

    stop = http.post(URL, data={"action": "stop"}, headers={"Prefer": "wait=60"})
    assert stop.status_code in (200, 202), stop.text  # 202: still decoding after 60 s
    job = finished_job(http, stop.json()["id"])
    assert job["id"] == done["job"] and job["state"] == "succeeded", job
    assert job["kind"] == "video" and job["frames_done"] == FRAMES
    assert 1 < done["camera_fps"] <= 16  # the camera's 15 frames/s, slower on a busy host
    assert job["options"]["fps"] == done["camera_fps"]  # no fps asked: the camera's rate
    assert job["info"]["keyframes"] >= 1 and job["info"]["paths"]["temporal"] > 0.5

    hdr10 = http.get(f"/v1/videos/{job['id']}/result", params={"output": "hdr10"})
    assert hdr10.status_code == 200
    with av.open(io.BytesIO(hdr10.content)) as container:
        stream = container.streams.video[0]
        assert stream.codec_context.name == "hevc"
        assert sum(1 for _ in container.decode(stream)) == FRAMES
    exr = http.get(f"/v1/videos/{job['id']}/result", params={"output": "exr_zip"})
    with zipfile.ZipFile(io.BytesIO(exr.content)) as archive:
        names = archive.namelist()
        assert len(names) == FRAMES
        for offset in (0, FRAMES // 2, FRAMES - 1):
            truth = camera.ground_truth(done["first_sequence"] + offset)
            gain = truth.params.gain or 1.0
            x_hat = read_hdr(archive.read(names[offset])).pixels * gain
            x_exact_w = reconstruct(truth.codes, truth.winding, truth.params)
            exact_w = np.abs(x_hat - x_exact_w) < 0.5
            assert exact_w.mean() >= 0.99, f"frame {offset}: W wrong on {1 - exact_w.mean():.2%}"
            relative = np.abs(x_hat - truth.irradiance) / truth.irradiance
            assert np.median(relative) < 0.01


def test_stop_mid_stream_and_bad_requests(camera: VirtualScamp5, client: Client) -> None:
    http = client(FULL_KEY)
    assert wait_for(lambda: http.get("/v1/devices/cam1").status_code == 200, 30)
    assert http.get(URL).status_code == 404
    nothing = http.post(URL, json={"action": "stop"})
    assert nothing.status_code == 409 and nothing.json()["code"] == "no_recording"
    bad = [
        ({"json": {"action": "fly"}}, 422, "action"),
        ({"json": {"mode": "temporal"}}, 422, "action"),
        ({"json": {"action": "start", "max_frames": 100_000}}, 422,
         "limit of 600 frames; ask for at most 600"),  # it did not say what to do
        ({"json": {"action": "start", "max_frames": 0}}, 422, "max_frames"),
        ({"json": {"action": "start", "decoder": "nope"}}, 422, "unknown decoder"),
        ({"json": {"action": "start", "outputs": "gif"}}, 422, "gif"),
        ({"json": {"action": "start", "colour": "red"}}, 422, "colour"),
        ({"json": ["start"]}, 422, "object"),
        ({"content": b"{no", "headers": {"Content-Type": "application/json"}}, 422, "JSON"),
        ({"content": b"[" * 50_000, "headers": {"Content-Type": "application/json"}}, 422,
         "JSON"),  # nested past Python's recursion limit: it gave 500
        ({"json": {"action": "start", "max_frames": True}}, 422, "not true"),  # it meant 1
        ({"json": {"action": "start", "max_frames": 10**400}}, 422, "less than"),
        ({"content": b'{"action": "start"}', "headers": {"Content-Type": "text/plain"}}, 422,
         "'text/plain' and was not read"),
    ]
    for request, status, fragment in bad:
        reply = http.post(URL, **request)
        assert reply.status_code == status, reply.text
        assert fragment in reply.text and reply.json()["code"] == "invalid_input"
    assert http.post("/v1/devices/nope/recordings", json={"action": "start"}).status_code == 404
    assert http.post("/v1/devices/bad!id/recordings", json={"action": "start"}).status_code == 422
    assert client(READ_KEY).post(URL, json={"action": "start"}).status_code == 403
    assert client("").get(URL).status_code == 401
    many = http.post(URL, data={f"f{n}": "x" for n in range(40)}, files={"f": ("a", b"a")})
    assert many.status_code == 400 and "Too many" in many.text, many.text

    fields = {"action": "start", "outputs": "exr_zip", "mode": "independent"}
    started = http.post(URL, params=fields)
    assert started.status_code == 201, started.text
    assert wait_for(lambda: recording(http)["frames"] >= 3, 30)
    stopped = http.post(URL, params={"action": "stop"})
    assert stopped.status_code == 202, stopped.text
    record = recording(http)
    assert record["state"] == "submitted" and record["reason"] == "requested"
    assert stopped.json()["id"] == record["job"]
    assert stopped.headers["location"] == record["job_url"]
    job = http.get(record["job_url"]).json()
    assert job["frames_total"] == record["frames"] >= 3
    assert job["options"]["mode"] == "independent" and job["options"]["outputs"] == ["exr_zip"]

    # No model for the camera's modulo frames: refused at the start (it was accepted, and
    # its stop failed, throwing the recorded frames away); the last recording stays.
    unmade = {"action": "start", "decoder": "mantissanet-base-noise", "outputs": "exr_zip"}
    refused = http.post(URL, json=unmade)
    assert refused.status_code == 422 and refused.json()["code"] == "invalid_input"
    assert "sends modulo frames of 256 x 256 px (its newest frame)" in refused.text
    assert "has no model for modulo frames (GET /v1/decoders" in refused.text
    assert recording(http) == record


def test_a_stop_waits_for_its_job_only_in_a_free_wait_slot(tmp_path: Path, redis_url: str) -> None:
    """Each stop waiting for the worker holds a server thread; with no 'Prefer: wait'
    slot free (none at all here) the stop answers at once with the recording, stopping,
    and the job follows there."""
    settings = make_settings(tmp_path, redis_url, max_waiting_requests=0)
    with serve(create_app(settings)) as url, live_camera(settings, tmp_path, fps=15, seed=4), \
            httpx.Client(base_url=url, headers={"Authorization": f"Bearer {FULL_KEY}"}) as http:
        assert wait_for(lambda: http.get("/v1/devices/cam1").status_code == 200, 30)
        assert http.post(URL, json={"action": "start"}).status_code == 201
        assert wait_for(lambda: recording(http)["frames"] >= 2, 30)
        stopped = http.post(URL, json={"action": "stop"})
        assert stopped.status_code == 202 and stopped.json()["state"] == "stopping"
        assert wait_for(lambda: recording(http)["job"] is not None, 30)


def test_a_stop_waits_for_its_video_job_no_longer_than_the_servers_limit(
    tmp_path: Path, redis_url: str
) -> None:
    """``Prefer: wait=600`` on a stop under ``MCAM_MAX_PREFER_WAIT_S`` 30 waits for the video
    job 30 s at the most: a 200 names the limit as the applied preference, a 202 none."""
    settings = make_settings(tmp_path, redis_url, max_prefer_wait_s=30.0)
    with serve(create_app(settings)) as url, live_camera(settings, tmp_path, fps=15, seed=5), \
            httpx.Client(base_url=url, headers={"Authorization": f"Bearer {FULL_KEY}"},
                         timeout=60) as http:
        assert wait_for(lambda: http.get("/v1/devices/cam1").status_code == 200, 30)
        start = {"action": "start", "outputs": "exr_zip", "mode": "independent"}
        assert http.post(URL, json=start).status_code == 201
        assert wait_for(lambda: recording(http)["frames"] >= 2, 30)
        stopped = http.post(URL, json={"action": "stop"}, headers={"Prefer": "wait=600"})
    assert stopped.status_code in (200, 202), stopped.text
    applied = "wait=30" if stopped.status_code == 200 else None
    assert stopped.headers.get("Preference-Applied") == applied


def test_a_stop_answers_409_when_the_worker_could_not_make_the_video_job(
    tmp_path: Path, redis_url: str
) -> None:
    """A camera that stopped streaming (after 3 frames) sends no frame between the start
    and the stop: the worker fails the recording, and the stop says why instead of
    answering 202 with a job that will never come. A server whose limit of 1000 code
    values no 256 x 256 px frame fits refuses the start once the device reported one."""
    settings = make_settings(tmp_path, redis_url)
    small = make_settings(tmp_path, redis_url, max_video_samples=1000)
    with serve(create_app(settings)) as url, serve(create_app(small)) as small_url, \
            live_camera(settings, tmp_path, fps=15, seed=6, max_frames=3), \
            httpx.Client(headers={"Authorization": f"Bearer {FULL_KEY}"}, timeout=60) as http:
        http.base_url = httpx.URL(url)
        assert wait_for(lambda: "/000000000002-" in str(
            http.get("/v1/devices/cam1").json().get("latest_result")), 30)  # all 3 decoded
        refused = http.post(f"{small_url}{URL}", json={"action": "start"})
        assert refused.status_code == 422, refused.text
        assert "one frame holds 65536 code values" in refused.text
        assert "MCAM_MAX_VIDEO_SAMPLES" in refused.text
        started = http.post(URL, json={"action": "start"})
        assert started.status_code == 201, started.text
        stopped = http.post(URL, json={"action": "stop"})
        assert stopped.status_code == 409, stopped.text
        body = stopped.json()
        assert body["code"] == "recording_failed"
        assert f"recording {started.json()['id']} failed: no frames were recorded" in (
            body["message"])
        assert recording(http)["state"] == "failed"


def test_a_start_racing_the_devices_forget_leaves_no_recording(
    settings: Settings, client: Client, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A start and a DELETE of a stopped device at once, the DELETE landing after the
    start found the device registered (held there until the DELETE answers: the order
    that lost it). Before, the start answered 201 for a device already forgotten, and its
    record, in state 'recording', stayed behind: it could not be stopped (404) and a
    daemon coming back weeks later recorded into it unasked."""
    redis_client = stopped_device(settings, "cam1")
    registered, forgotten = threading.Event(), threading.Event()
    reported_frames = recordings.reported_frames

    def held(*args: object) -> object:
        registered.set()
        forgotten.wait(30)
        return reported_frames(*args)

    monkeypatch.setattr(recordings, "reported_frames", held)
    together = threading.Barrier(2)
    replies: dict[str, httpx.Response] = {}

    def start() -> None:
        together.wait(10)
        replies["start"] = client(SUBMIT_KEY).post(URL, json={"action": "start"})

    def forget() -> None:
        together.wait(10)
        registered.wait(30)
        replies["delete"] = client(SUBMIT_KEY).delete("/v1/devices/cam1")
        forgotten.set()

    threads = [threading.Thread(target=start), threading.Thread(target=forget)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join(60)
    assert replies["delete"].status_code == 200, replies["delete"].text
    assert replies["start"].status_code == 404, replies["start"].text
    assert replies["start"].json()["code"] == "not_found"
    assert redis_client.exists(recording_key("cam1")) == 0


def test_a_stop_racing_a_start_answers_for_the_recording_it_found(
    settings: Settings, client: Client, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A stop and a start at once on a device whose last recording has ended, the start
    landing just after the stop's script ran (held there: the order that lost it). Before, the
    stop found nothing to stop, then read the record again and answered 202 with the new
    recording, still 'recording': the client was told it stopped a recording that ran
    on. The stop now answers for the recording it found (its end), as if it came first."""
    assert settings.redis_url is not None
    redis_client = connect(settings.redis_url)
    redis_client.sadd(DEVICES_SET, "cam1")
    http = client(FULL_KEY)
    ended = http.post(URL, json={"action": "start"}).json()
    recordings.request_stop(redis_client, "cam1")
    store = ResultStore(settings.data_dir / RESULTS_DIR, retention_s=60)
    Recorder(redis_client, store, max_deliveries=3).finish_if_due("cam1")
    assert recording(http)["state"] == "failed"  # no frames: no worker ran
    run_script = Script.__call__

    def start_after_the_stop(script: Script, *args: Any, **kwargs: Any) -> Any:
        result = run_script(script, *args, **kwargs)
        if script.script == recordings._STOP:
            monkeypatch.setattr(Script, "__call__", run_script)
            recordings.start_recording(redis_client, "cam1", decoder="itoh", options={},
                                       max_frames=10)
        return result

    monkeypatch.setattr(Script, "__call__", start_after_the_stop)
    together = threading.Barrier(2)
    replies: list[httpx.Response] = []

    def stop() -> None:
        together.wait(10)
        replies.append(http.post(URL, json={"action": "stop"}))

    thread = threading.Thread(target=stop)
    thread.start()
    together.wait(10)
    thread.join(60)
    (stopped,) = replies
    assert stopped.status_code == 409, stopped.text
    assert stopped.json()["code"] == "recording_failed"
    assert f"recording {ended['id']} failed" in stopped.json()["message"]
    assert recording(http)["state"] == "recording"


@pytest.mark.parametrize("frames", [2, 0])
def test_a_stop_whose_recording_a_new_start_replaced_meanwhile_answers_its_end(
    settings: Settings, client: Client, monkeypatch: pytest.MonkeyPatch, frames: int
) -> None:
    """A stop waits for the worker to queue the video job, looking at the record again
    and again. The worker queues it and another client starts a new recording between
    two looks (held there: the order that lost it). Before, the stop took the new
    recording for its own and answered 202 with it, still 'recording' and no job; it now
    answers with the video job of the recording it stopped (named by its id), or, with
    no frames recorded (no job made), with its failure."""
    assert settings.redis_url is not None
    redis_client = connect(settings.redis_url)
    redis_client.sadd(DEVICES_SET, "cam1")
    http = client(FULL_KEY)
    started = http.post(URL, json={"action": "start", "outputs": "exr_zip"}).json()
    store = ResultStore(settings.data_dir / RESULTS_DIR, retention_s=60)
    worker = Recorder(redis_client, store, max_deliveries=3)
    frame = simulate(scene(64), PARAMS)
    for sequence in range(frames):
        worker.add_frame(FrameMessage("cam1", sequence, sequence * 1000, frame.codes,
                                      frame.params, False), f"{7000 + sequence}-0")
    read = recording_routes.load_recording

    def finish_and_start_then_read(*args: Any) -> recordings.Recording | None:
        monkeypatch.setattr(recording_routes, "load_recording", read)
        worker.finish_if_due("cam1")
        recordings.start_recording(redis_client, "cam1", decoder="itoh", options={},
                                   max_frames=10)
        return read(*args)

    monkeypatch.setattr(recording_routes, "load_recording", finish_and_start_then_read)
    stopped = http.post(URL, json={"action": "stop"})
    if frames:
        assert stopped.status_code == 202, stopped.text
        assert stopped.json()["id"] == started["id"] and stopped.json()["state"] == "queued"
    else:
        assert stopped.status_code == 409, stopped.text
        assert f"recording {started['id']} failed" in stopped.json()["message"]
        assert "start a new recording" in stopped.json()["message"]
    assert recording(http)["state"] == "recording"


def test_a_start_without_max_frames_takes_the_servers_lower_frame_limit(
    tmp_path: Path, redis_url: str
) -> None:
    """A start that gives no ``max_frames`` on a server whose ``MCAM_MAX_VIDEO_FRAMES`` is
    below the default of 300 records up to that limit. Before, the README's plain
    ``action=start`` was refused 422, "max_frames 300 is above this server's limit of
    10 frames", a number the client never sent."""
    settings = make_settings(tmp_path, redis_url, max_video_frames=10)
    stopped_device(settings, "cam1")
    with serve(create_app(settings)) as url, \
            httpx.Client(base_url=url, headers={"Authorization": f"Bearer {FULL_KEY}"}) as http:
        started = http.post(URL, json={"action": "start"})
        assert started.status_code == 201, started.text
        assert started.json()["max_frames"] == 10
        asked = http.post(URL, json={"action": "start", "max_frames": 11})
        assert asked.status_code == 422 and "limit of 10 frames" in asked.text


def test_a_start_while_the_last_recording_is_stopping_says_so(
    settings: Settings, client: Client
) -> None:
    """A start while the last recording waits for the worker to make its video (stopped,
    the worker down or behind) is refused saying that, and what to do. Before, it said the
    device "is already recording; stop it first (action=stop)": a stop then changed
    nothing and the start was refused again."""
    redis_client = stopped_device(settings, "cam1")
    http = client(SUBMIT_KEY)
    assert http.post(URL, json={"action": "start"}).status_code == 201
    stopping = recordings.request_stop(redis_client, "cam1")
    refused = http.post(URL, json={"action": "start"})
    assert refused.status_code == 409 and refused.json()["code"] == "recording_running"
    message = refused.json()["message"]
    assert f"recording {stopping.id} was stopped" in message and "stop it first" not in message
    assert "is a worker running" in message and f"GET {URL}" in message


def test_a_stop_with_start_options_is_refused_and_stops_nothing(
    settings: Settings, client: Client
) -> None:
    """Video options and ``max_frames`` go with the start: a stop that sends them is
    refused naming them, and the recording goes on. Before, they were dropped without a
    word: a stop asking for ``outputs=sdr`` answered 202 with a job making the start's
    HDR10, SDR and EXR outputs."""
    stopped_device(settings, "cam1")
    http = client(FULL_KEY)
    assert http.post(URL, json={"action": "start"}).status_code == 201
    refused = http.post(URL, json={"action": "stop", "outputs": "sdr", "max_frames": 5})
    assert refused.status_code == 422 and refused.json()["code"] == "invalid_input"
    message = refused.json()["message"]
    assert "max_frames, outputs" in message and "action=start" in message
    assert recording(http)["state"] == "recording"


def test_a_start_on_a_full_redis_is_refused_503_and_leaves_no_recording(
    settings: Settings, client: Client
) -> None:
    """A start while Redis is at its maxmemory is refused 503 ``store_full`` saying what
    to do, and nothing is recorded. Before, it answered 201 "recording": the start's
    script deletes the old record before it writes, and Redis 6.2 checks a script's
    memory only at its first write, so the record was written although the camera's
    frames, the recording's progress and its video job could not be stored."""
    redis_client = stopped_device(settings, "cam1")
    http = client(FULL_KEY)
    redis_client.config_set("maxmemory", 1)
    try:
        refused = http.post(URL, json={"action": "start"})
    finally:
        redis_client.config_set("maxmemory", 0)
    assert refused.status_code == 503, refused.text
    assert refused.json()["code"] == "store_full"
    assert "MCAM_REDIS_MAXMEMORY" in refused.json()["message"]
    assert refused.headers["Retry-After"].isdigit()
    assert http.get(URL).status_code == 404
    assert http.post(URL, json={"action": "start"}).status_code == 201


def test_a_start_is_refused_when_redis_has_no_room_for_its_video(
    settings: Settings, client: Client
) -> None:
    """A start whose video (``max_frames`` of the device's newest frame size) would not
    fit in what Redis has free below its maxmemory is refused 503 ``store_full``, naming
    the room it needs; a shorter recording that fits starts."""
    redis_client = stopped_device(settings, "cam1")
    redis_client.hset(health_key("cam1"), "settings", json.dumps(
        {"encoding": "mantissa", "alpha": 2.0, "bits": 8, "gain": 1.0,
         "height": 64, "width": 64}
    ))
    http = client(FULL_KEY)
    leave_free(redis_client, 1 << 20)
    try:
        refused = http.post(URL, json={"action": "start", "max_frames": 300})
        started = http.post(URL, json={"action": "start", "max_frames": 10})
    finally:
        redis_client.config_set("maxmemory", 0)
    assert refused.status_code == 503, refused.text
    assert refused.json()["code"] == "store_full" and "max_frames" in refused.json()["message"]
    assert started.status_code == 201, started.text


def test_a_stop_after_the_recordings_video_job_expired_says_no_recording(
    settings: Settings, client: Client
) -> None:
    """A stop repeated after the recording's video job passed its retention (its record
    gone) answers 409 ``no_recording`` saying so. Before, it answered 404 "no job ...:
    submit the job again", from a device route the client had sent no job to."""
    redis_client = stopped_device(settings, "cam1")
    http = client(FULL_KEY)
    started = http.post(URL, json={"action": "start"}).json()
    redis_client.hset(recording_key("cam1"), mapping={"state": "submitted", "job": started["id"]})
    refused = http.post(URL, json={"action": "stop"})
    assert refused.status_code == 409, refused.text
    assert refused.json()["code"] == "no_recording"
    assert "expired" in refused.json()["message"] and "action=start" in refused.json()["message"]


def test_a_start_takes_outputs_as_the_list_a_recordings_view_shows(
    settings: Settings, client: Client
) -> None:
    """``GET /v1/devices/{id}/recordings`` shows ``options.outputs`` as a JSON list. Before,
    a start sending them back so got 422 "outputs: Input should be a valid string",
    which said neither that the field is comma-separated nor how to send it."""
    stopped_device(settings, "cam7")
    http = client(FULL_KEY)
    url = "/v1/devices/cam7/recordings"
    mixed = http.post(url, json={"action": "start", "outputs": ["sdr", 3]})
    assert mixed.status_code == 422 and mixed.json()["code"] == "invalid_input"
    started = http.post(url, json={"action": "start", "outputs": ["exr_zip", "sdr"]})
    assert started.status_code == 201, started.text
    assert recording(http, url)["options"]["outputs"] == ["exr_zip", "sdr"]
