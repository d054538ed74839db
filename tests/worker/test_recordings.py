"""Live recordings (``worker/recordings.py``, ``worker/recorder.py``,
``worker/recording_texts.py``) on a real redis-server and a real result store."""

from __future__ import annotations

import json
import threading
from pathlib import Path

import numpy as np
import pytest
import redis

from models.errors import InvalidInputError
from models.formation import SensorFrame
from worker import recordings
from worker.deliveries import StreamConsumer
from worker.device_consumer import DeviceConsumer
from worker.device_registry import DeviceNotFoundError
from worker.device_state import make_frame_decoder
from worker.frame_message import FrameMessage
from worker.jobs import JobRecord
from worker.queue import JobQueue, entry_codes, publish_frame
from worker.recorder import Recorder
from worker.recordings import (
    Recording,
    frame_key,
    load_recording,
    request_stop,
    start_recording,
)
from worker.redis_keys import (
    DEVICES_SET,
    JOBS_STREAM,
    frame_stream,
    health_key,
    recording_key,
)
from worker.result_store import ResultStore
from worker.video_input import WrappedVideo
from worker.video_jobs import DEFAULT_OPTIONS, video_options
from worker.video_output import padding_note
from worker.video_pipeline import decode_video_frames

OPTIONS = {"mode": "temporal", "outputs": ["exr_zip"]}


@pytest.fixture(autouse=True)
def registered(client: redis.Redis) -> None:
    """cam1 is registered, as its daemon's first health write or frame does."""
    client.sadd(DEVICES_SET, "cam1")


@pytest.fixture
def store(tmp_path: Path) -> ResultStore:
    return ResultStore(tmp_path / "results", retention_s=3600)


@pytest.fixture
def recorder(client: redis.Redis, store: ResultStore) -> Recorder:
    return Recorder(client, store, max_deliveries=3)


def message(frame: SensorFrame, sequence: int, discont: bool = False) -> FrameMessage:
    """A frame of a 10 frames/s camera."""
    return FrameMessage("cam1", sequence, sequence * 100_000_000, frame.codes, frame.params,
                        discont)


def frames(make_frame, count: int) -> list[SensorFrame]:  # type: ignore[no-untyped-def]
    return [make_frame(peak=4.0 + 0.05 * i) for i in range(count)]


def start(client: redis.Redis, max_frames: int = 100, options: dict | None = None):  # type: ignore[no-untyped-def]
    recording = start_recording(
        client, "cam1", decoder="itoh", options=options or OPTIONS, max_frames=max_frames
    )
    assert recording is not None and recording.state == "recording"
    return recording


def queued_codes(client: redis.Redis, job_id: str) -> np.ndarray:
    for _, fields in client.xrange(JOBS_STREAM):
        if fields[b"job"].decode() == job_id:
            return entry_codes({k.decode(): v for k, v in fields.items()})
    raise AssertionError(f"job {job_id} not on the jobs stream")


def test_frames_recorded_in_order_then_stopped_into_a_video_job(
    client: redis.Redis, recorder: Recorder, queue: JobQueue, store: ResultStore, make_frame
) -> None:
    clip = frames(make_frame, 6)
    recording = start(client)
    assert start_recording(client, "cam1", decoder="itoh", options=OPTIONS, max_frames=5) is None
    for i, frame in enumerate(clip[:3]):
        recorder.add_frame(message(frame, 10 + i), f"1000-{i}")
    recorder.add_frame(message(clip[2], 12), "1000-2")  # redelivered: not recorded twice
    recorder.add_frame(message(clip[3], 0, discont=True), "1000-3")  # camera reconnected
    recorder.add_frame(message(clip[4], 5), "1000-4")  # sequence gap
    recorder.add_frame(message(clip[5], 6), "1000-5")
    assert load_recording(client, "cam1").frames == 6
    assert store.exists(frame_key(recording.id, 5))

    recorder.finish_if_due("cam1")  # not asked to stop: nothing happens
    assert load_recording(client, "cam1").state == "recording"
    assert request_stop(client, "cam1").state == "stopping"
    recorder.add_frame(message(clip[0], 7), "1000-6")  # after the stop: not recorded
    recorder.finish_if_due("cam1")

    done = load_recording(client, "cam1")
    assert done.state == "submitted" and done.reason == "requested" and done.frames == 6
    assert done.keyframes == [3, 4]
    job = queue.get(done.job)
    assert job.kind == "video" and job.frames_total == 6 and job.decoder == "itoh"
    assert job.options["keyframes"] == [3, 4] and job.options["outputs"] == ["exr_zip"]
    codes = queued_codes(client, done.job)
    np.testing.assert_array_equal(codes, np.stack([f.codes for f in clip]))
    assert store.keys("recordings") == []  # the frames live on in the job entry only

    options, _ = video_options(job.decoder, job.options)
    decoded = decode_video_frames(WrappedVideo(codes, job.params), options)
    reasons = [frame["keyframe"] for frame in decoded.frames]
    assert reasons[0] == "first" and reasons[3] == reasons[4] == "discont"
    assert reasons[1] is None and reasons[5] is None
    assert start(client).id != recording.id  # a finished recording makes room for a new one


def test_max_frames_ends_the_recording(
    client: redis.Redis, recorder: Recorder, queue: JobQueue, make_frame
) -> None:
    start(client, max_frames=3)
    for i, frame in enumerate(frames(make_frame, 5)):
        recorder.add_frame(message(frame, i), f"2000-{i}")
    done = load_recording(client, "cam1")
    assert done.state == "submitted" and done.reason == "max_frames" and done.frames == 3
    assert queue.get(done.job).frames_total == 3
    assert request_stop(client, "cam1").job == done.job  # stopping again: the same job


@pytest.mark.parametrize("next_frame_first", [False, True])
def test_a_recording_whose_job_could_not_be_queued_at_max_frames_keeps_max_frames(
    client: redis.Redis, recorder: Recorder, queue: JobQueue, make_frame,
    monkeypatch: pytest.MonkeyPatch, next_frame_first: bool,
) -> None:
    """Redis refuses the video job when the last frame of ``max_frames`` comes (nearly
    full: the small record update fits, the codes do not), and that frame is retried
    once it has room. The recording ends with its ``max_frames`` frames, queued by the
    next poll or the next frame (the same batch), which is not recorded. Before, the
    retried frame was taken as recorded and nothing queued the job: the recording went
    on past ``max_frames`` and its video held a frame more than asked (more while Redis
    stayed full), or, with the camera stopped, it stayed "recording" until a stop."""
    start(client, max_frames=3)
    shots = frames(make_frame, 5)
    for i in range(2):
        recorder.add_frame(message(shots[i], i), f"2500-{i}")
    submit = recorder.queue.submit

    def full(*args, **kwargs):  # type: ignore[no-untyped-def]
        raise redis.exceptions.OutOfMemoryError("OOM command not allowed")

    monkeypatch.setattr(recorder.queue, "submit", full)
    with pytest.raises(redis.exceptions.OutOfMemoryError):
        recorder.add_frame(message(shots[2], 2), "2500-2")
    monkeypatch.setattr(recorder.queue, "submit", submit)
    recorder.add_frame(message(shots[2], 2), "2500-2")  # the retry, once Redis has room
    if next_frame_first:
        recorder.add_frame(message(shots[3], 3), "2500-3")
    recorder.finish_if_due("cam1")  # the next poll (the camera may have stopped sending)
    recorder.add_frame(message(shots[4], 4), "2500-4")
    done = load_recording(client, "cam1")
    assert done.state == "submitted" and done.reason == "max_frames" and done.frames == 3
    assert queue.get(done.job).frames_total == 3


def test_a_stop_after_its_job_was_refused_at_max_frames_records_no_more(
    client: redis.Redis, recorder: Recorder, queue: JobQueue, make_frame,
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """As above, with a stop before Redis has room again: a frame sent before the stop
    but handled after it is not recorded past ``max_frames`` either."""
    start(client, max_frames=3)
    shots = frames(make_frame, 4)
    for i, shot in enumerate(shots):
        publish_frame(client, message(shot, i), maxlen=100)
    entries = [entry.decode() for entry, _ in client.xrange(frame_stream("cam1"))]
    for i in range(2):
        recorder.add_frame(message(shots[i], i), entries[i])

    def full(*args, **kwargs):  # type: ignore[no-untyped-def]
        raise redis.exceptions.OutOfMemoryError("OOM command not allowed")

    with monkeypatch.context() as patch:
        patch.setattr(recorder.queue, "submit", full)
        with pytest.raises(redis.exceptions.OutOfMemoryError):
            recorder.add_frame(message(shots[2], 2), entries[2])
    request_stop(client, "cam1")
    recorder.add_frame(message(shots[2], 2), entries[2])  # the retry
    recorder.add_frame(message(shots[3], 3), entries[3])  # sent before the stop
    done = load_recording(client, "cam1")
    assert done.state == "submitted" and done.frames == 3
    assert queue.get(done.job).frames_total == 3


def test_changed_sensor_parameters_end_the_recording(
    client: redis.Redis, recorder: Recorder, queue: JobQueue, make_frame
) -> None:
    start(client)
    first, second = frames(make_frame, 2)
    recorder.add_frame(message(first, 0), "3000-0")
    noisy = first.params.model_copy(update={"seed": 99})  # a new noise seed is fine
    recorder.add_frame(FrameMessage("cam1", 1, 0, second.codes, noisy), "3000-1")
    brighter = first.params.model_copy(update={"gain": 2.0})
    recorder.add_frame(FrameMessage("cam1", 2, 0, second.codes, brighter), "3000-2")
    done = load_recording(client, "cam1")
    assert done.state == "submitted" and done.reason == "params_changed" and done.frames == 2
    assert queue.get(done.job).params.gain == first.params.gain


def test_a_video_cut_short_by_a_change_of_the_cameras_settings_says_so(
    client: redis.Redis, recorder: Recorder, queue: JobQueue, make_frame
) -> None:
    """A change of the camera's gain (``set_exposure``) or frame size ends the recording
    there. Before, the video job of a stop sent minutes later held only the frames before
    the change, its ``warnings`` []: nothing the stop answered said the recording had
    ended early, nor why."""
    first, second = frames(make_frame, 2)
    start(client)
    recorder.add_frame(message(first, 5), "3000-0")
    brighter = first.params.model_copy(update={"gain": 2.0})
    recorder.add_frame(FrameMessage("cam1", 6, 0, second.codes, brighter), "3000-1")
    [warning] = queue.get(load_recording(client, "cam1").job).warnings
    assert warning.startswith(
        "the recording ended by itself before the camera's frame 6, whose gain changed from "
        "1.0 to 2.0 (one video keeps one sensor setting): frames from then on are not in "
        "this video; start a new recording (POST /v1/devices/cam1/recordings")
    start(client)
    recorder.add_frame(message(first, 7), "3000-2")
    recorder.add_frame(message(make_frame(size=32), 8), "3000-3")
    [warning] = queue.get(load_recording(client, "cam1").job).warnings
    assert "frame 8, whose frame size changed from 64 x 64 to 32 x 32 (one video" in warning


def test_stop_without_frames_fails_with_a_reason(
    client: redis.Redis, recorder: Recorder, store: ResultStore
) -> None:
    assert request_stop(client, "cam1") is None  # never recorded
    start(client)
    request_stop(client, "cam1")
    recorder.finish_if_due("cam1")
    failed = load_recording(client, "cam1")
    assert failed.state == "failed" and failed.job is None
    assert "no frames were recorded" in failed.error


def test_a_stop_before_the_cameras_next_frame_says_no_frame_came_and_what_to_do(
    client: redis.Redis, recorder: Recorder
) -> None:
    """A stop that came before the camera's next frame (0.014 s after the start, on a
    camera at 5 frames/s) failed "is device 'cam1''s camera streaming ... and a worker
    running?" while both were (the worker that ended it ran). It now says no frame came
    in how long, and to record for longer or get the camera streaming."""
    client.hset(health_key("cam1"), "state", "connected")
    started = start(client)
    client.hset(recording_key("cam1"), "started_ns", started.started_ns - 14_000_000)
    request_stop(client, "cam1")
    recorder.finish_if_due("cam1")
    failed = load_recording(client, "cam1")
    assert failed.state == "failed" and "worker running" not in failed.error
    window_s = (failed.stopped_ns - failed.started_ns) / 1e9
    assert 0.014 <= window_s < 1.0
    assert (f"no frame reached device 'cam1''s stream in the {window_s:.3g} s between the "
            "start and the stop: record for longer than one frame") in failed.error


def test_a_recording_of_a_camera_whose_port_never_opened_says_why(
    client: redis.Redis, recorder: Recorder
) -> None:
    """A recording of a device whose daemon cannot open its camera's port ends saying
    so, naming the device. Before: "no frames were recorded: is the camera streaming
    (GET /v1/devices/{id}) and a worker running?", with the id left as ``{id}``."""
    client.hset(health_key("cam1"), mapping={
        "state": "connecting", "port_error": "/dev/ttyACM0 does not exist: check --port",
    })
    start(client)
    request_stop(client, "cam1")
    recorder.finish_if_due("cam1")
    failed = load_recording(client, "cam1")
    assert failed.state == "failed"
    assert "device 'cam1'" in failed.error and "{id}" not in failed.error
    assert "/dev/ttyACM0 does not exist: check --port" in failed.error


def test_a_recording_of_a_device_whose_daemon_crashed_says_so_and_what_to_do(
    client: redis.Redis, recorder: Recorder
) -> None:
    """A crashed daemon leaves its health ``crashed`` with the error in ``crash``: a
    recording of its device ended "no frames were recorded: is device 'cam1''s camera
    streaming ... and a worker running?", naming neither the crash nor what to do."""
    client.hset(health_key("cam1"), mapping={
        "state": "crashed", "crash": "RuntimeError: not a client mistake", "port_error": "",
    })
    start(client)
    request_stop(client, "cam1")
    recorder.finish_if_due("cam1")
    failed = load_recording(client, "cam1")
    assert failed.state == "failed"
    assert "the daemon of device 'cam1' stopped on an unexpected error" in failed.error
    assert "(RuntimeError: not a client mistake)" in failed.error
    assert "restart mcam device" in failed.error and "worker running" not in failed.error


@pytest.mark.parametrize(("decoder", "options", "fragment"), [
    ("itoh", {"mode": "temporal", "outputs": ["hdr10"]}, "HDR10 video needs frames"),
    ("itoh", {"mode": "temporal"}, "HDR10 video needs frames"),  # default outputs: hdr10 too
    ("mantissanet-base-noise", OPTIONS, "has no model for modulo frames"),
])
def test_a_recording_that_cannot_make_its_video_fails_on_its_first_frame(
    client: redis.Redis, recorder: Recorder, store: ResultStore, make_frame, decoder: str,
    options: dict, fragment: str,
) -> None:
    """32 x 32 modulo frames can make no HDR10 video, nor any video with a decoder that has
    no model for modulo: the recording fails on its first frame, with the reason, instead
    of recording frames that its stop would then throw away."""
    start_recording(client, "cam1", decoder=decoder, options=options, max_frames=100)
    recorder.add_frame(message(make_frame(size=32), 0), "4000-0")
    failed = load_recording(client, "cam1")
    assert failed.state == "failed" and failed.reason == "frames_refused", failed
    assert fragment in failed.error and "its first recorded frame" in failed.error
    assert failed.frames == 0 and failed.stopped_ns and store.keys() == []
    recorder.add_frame(message(make_frame(size=32), 1), "4000-1")
    assert load_recording(client, "cam1").frames == 0
    assert request_stop(client, "cam1").error == failed.error


def test_a_start_is_refused_when_the_devices_newest_frame_cannot_make_its_video(
    client: redis.Redis,
) -> None:
    """The daemon reports its newest frame's encoding and size: a decoder with no model for
    it, or HDR10 of frames too small, is refused at the start, leaving no recording."""
    settings = {"encoding": "modulo", "alpha": 2.0, "bits": 8, "gain": 0, "width": 48,
                "height": 40}
    client.hset(health_key("cam1"), "settings", json.dumps(settings))
    with pytest.raises(InvalidInputError, match="has no model for modulo frames") as refused:
        start_recording(client, "cam1", decoder="mantissanet-base-noise", options=OPTIONS,
                        max_frames=10)
    assert "'cam1' sends modulo frames of 40 x 48 px (its newest frame)" in str(refused.value)
    with pytest.raises(InvalidInputError, match="HDR10 video needs frames.*outputs=sdr,exr_zip"):
        start_recording(client, "cam1", decoder="itoh", options={"outputs": ["hdr10"]},
                        max_frames=10)
    assert load_recording(client, "cam1") is None
    assert start_recording(client, "cam1", decoder="itoh", options=OPTIONS, max_frames=10)


def test_a_recording_ends_before_a_frame_that_would_pass_its_sample_limit(
    client: redis.Redis, recorder: Recorder, make_frame
) -> None:
    """Three 16 x 16 frames fit a limit of 800 code values, the fourth would not: the
    recording's video is the three, and a frame alone above the limit fails it with the
    reason (a video job is one Redis value: a recording past 512 MB was never queued)."""
    start_recording(client, "cam1", decoder="itoh", options=OPTIONS, max_frames=100,
                    max_samples=800)
    for sequence in range(5):
        recorder.add_frame(message(make_frame(size=16), sequence), f"{4000 + sequence}-0")
    done = load_recording(client, "cam1")
    assert done.state == "submitted" and done.reason == "max_samples" and done.frames == 3
    assert queued_codes(client, done.job).shape[0] == 3
    start_recording(client, "cam1", decoder="itoh", options=OPTIONS, max_frames=100,
                    max_samples=200)
    recorder.add_frame(message(make_frame(size=16), 9), "5000-0")
    failed = load_recording(client, "cam1")
    assert failed.state == "failed" and failed.reason == "frames_refused"
    assert "one frame holds 256 code values, more than the recording's limit of 200" in (
        failed.error)


def test_a_video_cut_short_by_the_sample_limit_says_so(
    client: redis.Redis, recorder: Recorder, queue: JobQueue, make_frame
) -> None:
    """A recording that reaches the server's ``MCAM_MAX_VIDEO_SAMPLES`` before its
    ``max_frames`` ends there. Before, the video job a later stop answered with held the
    frames so far, its ``warnings`` []: nothing said the video ended early, nor why."""
    start_recording(client, "cam1", decoder="itoh", options=OPTIONS, max_frames=100,
                    max_samples=800)
    for sequence in range(4):
        recorder.add_frame(message(make_frame(size=16), 20 + sequence), f"{4000 + sequence}-0")
    [warning] = queue.get(load_recording(client, "cam1").job).warnings
    assert warning == (
        "the recording ended by itself before the camera's frame 23: with it the video "
        "would hold more than the server's limit of 800 code values (MCAM_MAX_VIDEO_SAMPLES; "
        "3 frames of this size fit; record fewer frames at a time with max_frames, or raise "
        "the limit): frames from then on are not in this video; start a new recording (POST "
        "/v1/devices/cam1/recordings action=start) to record them"
    )


def test_a_start_is_refused_when_one_of_the_devices_frames_passes_its_sample_limit(
    client: redis.Redis,
) -> None:
    """A start whose ``max_samples`` (the server's ``MCAM_MAX_VIDEO_SAMPLES``) is below
    one of the device's frames could never record one. Before, it answered 201, and the
    recording failed on its first frame ("one frame holds more code values than the
    recording's limit of 10000", naming neither the frame's size nor its count): seen
    with ``MCAM_MAX_VIDEO_SAMPLES=10000`` and a camera of 256 x 256 px frames."""
    settings = {"encoding": "modulo", "alpha": 2.0, "bits": 8, "gain": 1.0, "width": 256,
                "height": 256}
    client.hset(health_key("cam1"), "settings", json.dumps(settings))
    with pytest.raises(InvalidInputError) as refused:
        start_recording(client, "cam1", decoder="itoh", options=OPTIONS, max_frames=10,
                        max_samples=10_000)
    assert ("'cam1' sends modulo frames of 256 x 256 px (its newest frame), which this "
            "recording cannot make into a video: one frame holds 65536 code values, more "
            "than the recording's limit of 10000") in str(refused.value)
    assert "MCAM_MAX_VIDEO_SAMPLES" in str(refused.value)
    assert load_recording(client, "cam1") is None
    assert start_recording(client, "cam1", decoder="itoh", options=OPTIONS, max_frames=10,
                           max_samples=65_536)


def test_a_stop_whose_job_was_queued_but_not_noted_queues_it_once(
    client: redis.Redis, recorder: Recorder, make_frame, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Redis fails between queueing the video job and noting it on the recording: the
    recording stays stopping, and the next try finds the job (named by the recording)
    instead of queueing a second one."""
    recording = start(client)
    recorder.add_frame(message(make_frame(), 0), "6000-0")
    request_stop(client, "cam1")
    note = recorder._set

    def failing(recording, fields, **kwargs):  # type: ignore[no-untyped-def]
        if fields.get("state") == "submitted":
            raise redis.ConnectionError("Redis went away")
        return note(recording, fields, **kwargs)

    monkeypatch.setattr(recorder, "_set", failing)
    with pytest.raises(redis.ConnectionError):
        recorder.finish_if_due("cam1")
    assert load_recording(client, "cam1").state == "stopping"
    monkeypatch.setattr(recorder, "_set", note)
    recorder.finish_if_due("cam1")
    done = load_recording(client, "cam1")
    assert done.state == "submitted" and done.job == recording.id
    assert client.xlen(JOBS_STREAM) == 1


def test_frames_without_a_recording_are_ignored(
    client: redis.Redis, recorder: Recorder, store: ResultStore, make_frame
) -> None:
    recorder.add_frame(message(make_frame(), 0), "5000-0")
    recorder.finish_if_due("cam1")
    assert load_recording(client, "cam1") is None and store.keys() == []
    with pytest.raises(ValueError, match="max_frames"):
        start_recording(client, "cam1", decoder="itoh", options=OPTIONS, max_frames=0)


def test_a_start_for_a_device_not_registered_leaves_no_record(client: redis.Redis) -> None:
    """A device forgotten (or never registered) gets no recording: the registration is
    checked in the step that writes the record, so a forget that came between the API's
    look at the device and the start leaves nothing behind."""
    client.srem(DEVICES_SET, "cam1")
    with pytest.raises(DeviceNotFoundError, match="no device 'cam1'"):
        start_recording(client, "cam1", decoder="itoh", options=OPTIONS, max_frames=10)
    assert client.exists(recording_key("cam1")) == 0


def test_a_stop_finished_by_two_owners_at_once_stays_submitted(
    client: redis.Redis, store: ResultStore, queue: JobQueue, make_frame,
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Two workers owning the device at once (one stalled past its lease) both finish a
    stopping recording, the second having read it stopping just before the first queued
    its job and removed its frames (the order is held here). Before, the second found the
    frames gone and failed the recording over the first's 'submitted': the stop answered
    409 recording_failed ("no result ... never written or expired") with its job queued."""
    first, second = (Recorder(client, store, max_deliveries=3) for _ in range(2))
    start(client)
    for sequence, frame in enumerate(frames(make_frame, 3)):
        first.add_frame(message(frame, sequence), f"{6000 + sequence}-0")
    request_stop(client, "cam1")
    read = recordings.load_recording

    def read_then_first_finishes(*args: object) -> recordings.Recording | None:
        recording = read(*args)
        monkeypatch.setattr("worker.recorder.load_recording", read)
        first.finish_if_due("cam1")
        return recording

    monkeypatch.setattr("worker.recorder.load_recording", read_then_first_finishes)
    second.finish_if_due("cam1")
    done = read(client, "cam1")
    assert done.state == "submitted" and done.error is None, done
    assert queue.get(done.job).frames_total == 3


def test_frames_taken_while_the_worker_was_down_are_recorded_by_capture_time(
    client: redis.Redis, recorder: Recorder, queue: JobQueue, make_frame
) -> None:
    """A recording holds the frames the camera sent between its start and its stop, also
    when the worker handles them later (it was down, or behind). Before, it held the frames
    the worker happened to handle while the record said ``recording``: a start and a stop
    while the worker was down ended ``failed`` ("no frames were recorded") with the frames
    of that time waiting on the stream, and a worker behind recorded frames from before
    the start."""
    clip = frames(make_frame, 5)
    stream = frame_stream("cam1")

    def published(sequence: int) -> str:
        return client.xadd(stream, message(clip[sequence], sequence).to_fields()).decode()

    def handled(entry_id: str) -> None:
        """What the worker does with an entry: record the frame, commit (delete) it."""
        fields = client.xrange(stream, entry_id, entry_id)[0][1]
        recorder.add_frame(FrameMessage.from_fields(fields), entry_id)
        client.xdel(stream, entry_id)
        recorder.finish_if_due("cam1")

    before = published(0)
    start(client)
    during = [published(1), published(2), published(3)]
    request_stop(client, "cam1")
    after = published(4)
    for entry_id in [before, *during]:
        handled(entry_id)
        assert load_recording(client, "cam1").state == ("submitted" if entry_id == during[-1]
                                                       else "stopping")
    handled(after)
    done = load_recording(client, "cam1")
    assert done.frames == 3 and done.reason == "requested"
    np.testing.assert_array_equal(queued_codes(client, done.job),
                                  np.stack([f.codes for f in clip[1:4]]))


def timed(frame: SensorFrame, sequence: int, t_ns: int, discont: bool = False) -> FrameMessage:
    return FrameMessage("cam1", sequence, t_ns, frame.codes, frame.params, discont)


def stopped_job(client: redis.Redis, recorder: Recorder, queue: JobQueue) -> JobRecord:
    """Stop cam1's recording and return the video job its frames made."""
    request_stop(client, "cam1")
    recorder.finish_if_due("cam1")
    return queue.get(load_recording(client, "cam1").job)


def test_a_video_without_fps_plays_at_the_cameras_rate(
    client: redis.Redis, recorder: Recorder, queue: JobQueue, make_frame
) -> None:
    clip = frames(make_frame, 5)
    start(client)
    step_ns = 100_000_000  # a 10 frames/s camera
    recorder.add_frame(timed(clip[0], 40, 5 * step_ns), "1000-0")
    recorder.add_frame(timed(clip[1], 41, 6 * step_ns), "1000-1")
    recorder.add_frame(timed(clip[2], 43, 8 * step_ns), "1000-2")  # one frame dropped
    recorder.add_frame(timed(clip[3], 0, 10**15, discont=True), "1000-3")  # camera restarted
    recorder.add_frame(timed(clip[4], 1, 10**15 + step_ns), "1000-4")
    assert load_recording(client, "cam1").view()["camera_fps"] == 10.0
    assert stopped_job(client, recorder, queue).options["fps"] == 10.0


def test_a_camera_faster_than_any_video_rate_is_shown_as_is_and_warned_of(
    client: redis.Redis, recorder: Recorder, queue: JobQueue, make_frame
) -> None:
    """A camera may run at up to 10,000 frames/s, a video plays at up to 1000. Before,
    a recording of a 2000 frames/s camera showed ``camera_fps`` 1000 and its video
    played at half the camera's speed without a word. The recording now shows the
    camera's rate, and the video (at 1000 frames/s) warns that it plays slower."""
    clip = frames(make_frame, 3)
    start(client)
    for i, frame in enumerate(clip):
        recorder.add_frame(timed(frame, 10 + i, i * 500_000), f"1000-{i}")  # 0.5 ms apart
    assert load_recording(client, "cam1").view()["camera_fps"] == 2000.0
    job = stopped_job(client, recorder, queue)
    assert job.options["fps"] == 1000.0
    assert job.warnings == [
        "the camera ran at 2000 frames/s, faster than the 1000 frames/s a video plays at: "
        "this video plays at 1000 frames/s, 2x slower than the camera; to choose its rate, "
        "give fps with action=start"
    ]


def test_a_start_that_names_fps_keeps_it(
    client: redis.Redis, recorder: Recorder, queue: JobQueue, make_frame
) -> None:
    clip = frames(make_frame, 2)
    start(client, options={**OPTIONS, "fps": 24.0})
    recorder.add_frame(timed(clip[0], 1, 0), "1000-0")
    recorder.add_frame(timed(clip[1], 2, 100_000_000), "1000-1")
    assert stopped_job(client, recorder, queue).options["fps"] == 24.0


def test_a_rate_not_measured_leaves_the_default_fps(
    client: redis.Redis, recorder: Recorder, queue: JobQueue, make_frame
) -> None:
    start(client)
    recorder.add_frame(timed(frames(make_frame, 1)[0], 1, 0), "1000-0")
    assert load_recording(client, "cam1").view()["camera_fps"] is None
    job = stopped_job(client, recorder, queue)
    assert video_options(job.decoder, job.options)[0].hdr10.fps == DEFAULT_OPTIONS["fps"]


def test_a_bracket_inside_a_recording_is_no_frame_lost_and_no_frame_period(
    client: redis.Redis, recorder: Recorder, queue: JobQueue, make_frame
) -> None:
    """A bracketed capture's packets take the camera's sequence numbers but are never
    streamed. Before, a recording across a bracket (``POST /v1/devices/{id}/control``
    ``bracket``, 6 packets) counted them in ``frames_skipped``, its video warned of 6
    frames "lost on the camera link" (check the cable) while none was, and its camera
    rate counted the bracket's steps as frame periods (5.7 frames/s for a 5 frames/s
    camera)."""
    clip = frames(make_frame, 4)
    start(client)
    step_ns = 100_000_000  # a 10 frames/s camera; the bracket takes one tick
    recorder.add_frame(timed(clip[0], 10, 10 * step_ns), "1000-0")
    recorder.add_frame(timed(clip[1], 11, 11 * step_ns), "1000-1")
    after = FrameMessage("cam1", 18, 13 * step_ns, clip[2].codes, clip[2].params, bracketed=6)
    recorder.add_frame(after, "1000-2")
    recorder.add_frame(timed(clip[3], 19, 14 * step_ns), "1000-3")
    view = load_recording(client, "cam1").view()
    assert (view["frames_skipped"], view["camera_fps"]) == (0, 10.0)
    job = stopped_job(client, recorder, queue)
    assert job.warnings == [] and job.options["fps"] == 10.0


def late_worker(client: redis.Redis, store: ResultStore) -> DeviceConsumer:
    """A worker's device side (itoh), started after the frames were sent."""
    return DeviceConsumer(
        client, store, owner="w1", lease_ms=5000, max_deliveries=3,
        decode=make_frame_decoder("independent", "itoh"), stop=threading.Event(),
    )  # fmt: skip


def ended(client: redis.Redis, worker: DeviceConsumer, wait_until) -> Recording:  # type: ignore[no-untyped-def]
    """Poll ``worker`` until cam1's recording has ended; return it."""
    def has_ended() -> bool:
        worker.poll()
        return load_recording(client, "cam1").state not in ("recording", "stopping")

    wait_until(has_ended, what="the recording to end")
    return load_recording(client, "cam1")


def test_a_recording_whose_frames_were_all_trimmed_says_how_many_and_what_to_do(
    client: redis.Redis, store: ResultStore, make_frame, wait_until
) -> None:
    """Frames wait on a stream of MCAM_FRAMES_MAXLEN entries; with no worker reading it,
    the oldest are trimmed. Before, a recording whose frames were all trimmed failed with
    "no frames were recorded: is the camera streaming ... and a worker running?", which
    did not say that the camera did stream and the frames were lost."""
    clip = frames(make_frame, 2)
    for sequence in range(2):  # before the start: trimmed too, not the recording's
        publish_frame(client, message(clip[0], sequence), maxlen=4)
    start(client)
    for sequence in range(2, 7):
        publish_frame(client, message(clip[sequence % 2], sequence), maxlen=4)
    request_stop(client, "cam1")
    for sequence in range(7, 11):  # after the stop: they push the recording's frames out
        publish_frame(client, message(clip[sequence % 2], sequence), maxlen=4)

    failed = ended(client, late_worker(client, store), wait_until)
    assert failed.state == "failed" and failed.frames == 0 and failed.frames_lost == 5
    assert "5 frames the camera sent between the start and the stop" in failed.error
    assert "keep a worker running" in failed.error and "MCAM_FRAMES_MAXLEN" in failed.error
    assert "stream_full in GET /v1/devices/cam1)" in failed.error, failed.error  # not {id}


def test_a_video_that_lost_frames_to_the_full_stream_says_how_many(
    client: redis.Redis, store: ResultStore, queue: JobQueue, make_frame, wait_until
) -> None:
    """Before, a recording that lost some of its frames to the full device stream made
    its video of the rest without a word: its record and its job said nothing of the
    loss. Frames a worker read before the stream dropped them are in its hands, and
    recorded: they are not counted."""
    clip = frames(make_frame, 2)
    start(client)
    publish_frame(client, message(clip[0], 0), maxlen=3)
    held = StreamConsumer(client, frame_stream("cam1"), "w0", max_deliveries=3)
    [read] = held.read_new(block_ms=None)  # a worker holds frame 0 when the stream drops it
    for sequence in range(1, 7):  # frames 1-3 are dropped before any worker read them
        publish_frame(client, message(clip[sequence % 2], sequence), maxlen=3)
    Recorder(client, store, max_deliveries=3).add_frame(FrameMessage.from_fields(read.fields),
                                                        read.entry_id)
    held.done(read)
    request_stop(client, "cam1")

    done = ended(client, late_worker(client, store), wait_until)
    assert done.state == "submitted" and done.frames == 4 and done.frames_lost == 3
    assert done.view()["frames_lost"] == 3
    [warning] = queue.get(done.job).warnings
    assert warning.startswith("3 frames the camera sent between the start and the stop")
    assert "MCAM_FRAMES_MAXLEN" in warning
    assert "stream_full in GET /v1/devices/cam1)" in warning, warning  # it said {id}


def test_a_video_that_lacks_frames_lost_on_the_camera_link_says_how_many(
    client: redis.Redis, recorder: Recorder, queue: JobQueue, make_frame
) -> None:
    """Frames lost on the camera link (corrupt or truncated packets, a disconnect) or
    dropped by the daemon never reach the stream. Before, the video of a recording that
    lacked them said nothing (``warnings`` []; the daemon's health counted them only):
    seen with ``mcam simulate-device --drop 0.2``, 52 of 60 frames and no warning. A
    step back of the camera's counter (a restart) is no loss."""
    clip = frames(make_frame, 5)
    start(client)
    for i, sequence in enumerate((10, 11, 14, 2, 3)):  # 12 and 13 lost; then a restart
        recorder.add_frame(message(clip[i], sequence, discont=sequence == 2), f"3000-{i}")
    assert load_recording(client, "cam1").view()["frames_skipped"] == 2
    request_stop(client, "cam1")
    recorder.finish_if_due("cam1")

    done = load_recording(client, "cam1")
    assert done.state == "submitted" and done.frames == 5 and done.frames_skipped == 2
    [warning] = queue.get(done.job).warnings
    assert warning.startswith("2 frames the camera numbered between the recording's first")
    assert "lost on the camera link" in warning and "GET /v1/devices/cam1 counts" in warning


def test_frames_a_stopped_worker_held_when_the_stream_dropped_them_count_as_lost(
    client: redis.Redis, store: ResultStore, make_frame, wait_until
) -> None:
    """A worker that read frames and stopped before recording them leaves them pending;
    the full stream then drops them, and the next owner finds them without their data.
    Before, it acked them without a word: the video lacked them and ``frames_lost`` said
    0 (all lost: "is a worker running?")."""
    clip = frames(make_frame, 2)
    start(client)
    for sequence in range(3):
        publish_frame(client, message(clip[sequence % 2], sequence), maxlen=3)
    stopped = StreamConsumer(client, frame_stream("cam1"), "w0", max_deliveries=3)
    assert len(stopped.read_new(block_ms=None, count=10)) == 3
    for sequence in range(3, 5):  # frames 0 and 1 go while w0 holds them
        publish_frame(client, message(clip[sequence % 2], sequence), maxlen=3)
    request_stop(client, "cam1")

    done = ended(client, late_worker(client, store), wait_until)
    assert done.state == "submitted" and done.frames == 3 and done.frames_lost == 2


def overflowing(frame: SensorFrame, sequence: int) -> FrameMessage:
    """A frame whose scene-referred reconstruction (x / gain) is beyond float32."""
    tiny_gain = frame.params.model_copy(update={"gain": 2.3e-308})
    return FrameMessage("cam1", sequence, sequence * 1000, frame.codes, tiny_gain)


def test_a_recording_whose_frames_all_failed_to_decode_says_why(
    client: redis.Redis, store: ResultStore, make_frame, wait_until
) -> None:
    """A camera streams frames the worker cannot reconstruct (here: a gain so small
    that x / gain passes float32). Before, the recording failed with "no frames were
    recorded: is the camera streaming (GET /v1/devices/{id}) and a worker running?",
    though both were; now it says how many frames failed and the last one's error."""
    [frame] = frames(make_frame, 1)
    start(client)
    for sequence in range(3):
        publish_frame(client, overflowing(frame, sequence), maxlen=100)
    request_stop(client, "cam1")

    failed = ended(client, late_worker(client, store), wait_until)
    assert failed.state == "failed" and failed.frames == 0 and failed.frames_failed == 3
    assert failed.view()["frames_failed"] == 3
    assert "3 frames the camera sent between the start and the stop failed" in failed.error
    assert "output_overflow" in failed.error and "a worker running" not in failed.error


def test_a_video_whose_frames_partly_failed_to_decode_warns_of_them(
    client: redis.Redis, store: ResultStore, queue: JobQueue, make_frame, wait_until
) -> None:
    """Frames that fail to decode are left out of the video (the next one is a
    keyframe); its job warns how many, and why the last failed."""
    clip = frames(make_frame, 3)
    start(client)
    publish_frame(client, message(clip[0], 0), maxlen=100)
    publish_frame(client, overflowing(clip[1], 1), maxlen=100)
    publish_frame(client, message(clip[2], 2), maxlen=100)
    request_stop(client, "cam1")

    done = ended(client, late_worker(client, store), wait_until)
    assert done.state == "submitted" and done.frames == 2 and done.frames_failed == 1
    assert done.keyframes == [1]
    [warning] = queue.get(done.job).warnings
    assert warning.startswith("1 frame the camera sent between the start and the stop failed")
    assert "output_overflow" in warning


def test_a_failed_frame_delivered_again_is_counted_once(
    client: redis.Redis, recorder: Recorder
) -> None:
    """A frame given up on whose ack did not happen (Redis went away) is given up again
    on its redelivery: it is one frame missing from the video, not two."""
    start(client)
    recorder.count_failed("cam1", "7000-0", "output_overflow: too bright")
    recorder.count_failed("cam1", "7000-0", "output_overflow: too bright")
    recorder.count_failed("cam1", "7000-1", "invalid_input: the last")
    recording = load_recording(client, "cam1")
    assert recording.frames_failed == 2 and recording.failed_error == "invalid_input: the last"


def test_a_video_of_frames_with_an_odd_side_says_its_mp4_videos_are_padded(
    client: redis.Redis, recorder: Recorder, queue: JobQueue, make_frame
) -> None:
    """A recording's MP4 videos of 65 x 65 frames are 66 x 66, as 4:2:0 needs. Before,
    its job said nothing of it, where a job of ``POST /v1/videos`` of such frames warns
    (:func:`worker.video_output.padding_note`, the same words)."""
    clip = [make_frame(size=65, peak=4.0 + 0.05 * i) for i in range(2)]
    start(client, options={"mode": "independent", "outputs": ["hdr10", "exr_zip"]})
    for i, frame in enumerate(clip):
        recorder.add_frame(message(frame, i), f"8000-{i}")
    request_stop(client, "cam1")
    recorder.finish_if_due("cam1")

    done = load_recording(client, "cam1")
    assert done.state == "submitted" and done.frames == 2
    [warning] = queue.get(done.job).warnings
    assert warning == padding_note(["hdr10"], 65, 65)
    assert warning.startswith("the MP4 videos are 66 x 66: 4:2:0 video needs even sides")
