"""Live recordings: a device's frames, as its worker handles them, collected into a video job.

This module holds the record (:class:`Recording`), its Redis keys and its start and stop
(the API's side); the worker's side, which records frames and queues the video job, is
:mod:`worker.recorder`, and what a recording misses is told by
:mod:`worker.recording_texts`.

Usage (API: writes the intent, reads the record)::

    record = start_recording(client, "cam1", decoder="itoh", options={...}, max_frames=300)
    record = request_stop(client, "cam1")    # state "stopping"; the worker submits the job
    record = load_recording(client, "cam1")  # None if the device never recorded

The record is the hash ``device:<id>:recording``; its ``state`` goes ``recording`` ->
``stopping`` (asked by the API) -> ``submitted`` (the video job is queued, its id in
``job``) or ``failed`` (``error`` says why). A recording also ends by itself after
``max_frames`` frames, before a frame that would take its code values past
``max_samples`` (a video job is one Redis value), or when the camera's sensor parameters
(other than the noise seed) or frame shape change: the frames so far become the video.
A recording holds the frames its camera sent between the start and the stop, however
late the worker handles them (it was down, or behind): the start and the stop note the
newest entry of the device's frame stream then (``start_entry``, ``stop_entry``), the
frames after the first and up to the second are recorded, and a stopping recording
becomes its video once no entry up to ``stop_entry`` is left on the stream. Each recorded
frame's codes (DN) are stored as ``recordings/<recording id>/<index:06d>.npy`` in the
result store until the job is queued. A frame flagged DISCONT, or one after a
sequence gap, is listed in ``keyframes`` (its index in the video), which the video
job decodes as a keyframe. A redelivered frame (stream entry at or before
``last_entry``) is not recorded twice; a new owner of the device goes on recording.

A recording whose video job could never be made from the device's frames (a decoder
with no model for their encoding, or ``hdr10`` among the outputs of frames under 64 px:
the checks ``POST /v1/videos`` makes; or frames each of more code values than
``max_samples``: :func:`check_recordable`) is refused before any
frame is kept: at the start, when the device's daemon reports its newest frame's
encoding and size (its health ``settings``), and otherwise on the first frame recorded.
A start refused is an :class:`InvalidInputError` (the API's 422) and leaves no record.
A recording refused on its first frame ends ``failed`` with reason ``frames_refused``
and ``error`` saying what was wrong and what to ask for instead; that frame is not
stored (it is still reconstructed as a device frame), so nothing already recorded is
lost, and a stop answers with that error. Frames of one recording keep one encoding
and size (a change ends it), so its first frame stands for all of them.
"""

from __future__ import annotations

import json
import time
import uuid
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import redis

from models.errors import InvalidInputError
from models.formation import SensorParams
from worker.deliveries import entry_order
from worker.device_registry import DeviceNotFoundError
from worker.queue import check_decoder_supports
from worker.redis_keys import DEVICES_SET, frame_stream, health_key, recording_key
from worker.redis_memory import StoreFullError, free_memory, submit_room
from worker.video_jobs import check_frame_size, video_options
from worker.video_output import FPS_RANGE

#: States of a recording that still collects frames or waits for its video job.
ACTIVE_STATES = ("recording", "stopping")
#: Most code values (frames x pixels x channels) of a recorded video unless the API sets
#: its own (``MCAM_MAX_VIDEO_SAMPLES``): a video job is one Redis value, 2 bytes a code,
#: and Redis takes at most 512 MB (a 618 MiB recording's job was refused on every try).
MAX_RECORDING_SAMPLES = 2**26

# The id of the newest entry on the frame stream (KEYS[n]; '0-0' when none waits): the
# frames sent up to then are those at or before it.
_NEWEST_ENTRY = """
local function newest_entry(stream)
  local newest = redis.call('XREVRANGE', stream, '+', '-', 'COUNT', 1)
  if #newest == 0 then return '0-0' end
  return newest[1][1]
end
"""

# KEYS: the recording, the devices set, the frame stream. ARGV: the device, then the
# record's fields. -1: the device is not registered (a forget came first); 0: a
# recording is active.
_START = _NEWEST_ENTRY + """
if redis.call('SISMEMBER', KEYS[2], ARGV[1]) == 0 then return -1 end
local state = redis.call('HGET', KEYS[1], 'state')
if state == 'recording' or state == 'stopping' then return 0 end
local fields = {'start_entry', newest_entry(KEYS[3])}
for i = 2, #ARGV do fields[#fields + 1] = ARGV[i] end
redis.call('DEL', KEYS[1])
redis.call('HSET', KEYS[1], unpack(fields))
return 1
"""

# Stops a running recording; returns the record (after the stop) in the same step.
# KEYS: the recording, the frame stream.
_STOP = _NEWEST_ENTRY + """
if redis.call('HGET', KEYS[1], 'state') == 'recording' then
  redis.call('HSET', KEYS[1], 'state', 'stopping', 'reason', 'requested', 'stopped_ns', ARGV[1],
             'stop_entry', newest_entry(KEYS[2]))
end
return redis.call('HGETALL', KEYS[1])
"""

@dataclass(frozen=True)
class Recording:
    """One recording of a device (times in ns since the epoch; ``keyframes``: frame indices)."""

    id: str
    device: str
    state: str
    decoder: str
    options: dict[str, Any]
    max_frames: int
    max_samples: int = MAX_RECORDING_SAMPLES
    frames: int = 0
    started_ns: int = 0
    stopped_ns: int | None = None
    reason: str | None = None
    keyframes: list[int] = field(default_factory=list)
    params: str = ""
    shape: str = ""
    first_sequence: int | None = None
    last_sequence: int | None = None
    last_ts_ns: int | None = None
    camera_steps: int = 0
    camera_span_ns: int = 0
    last_entry: str | None = None
    start_entry: str | None = None
    stop_entry: str | None = None
    frames_lost: int = 0
    frames_failed: int = 0
    frames_skipped: int = 0
    failed_error: str | None = None
    job: str | None = None
    error: str | None = None

    @classmethod
    def from_hash(cls, raw: dict[bytes, bytes]) -> Recording:
        """Parse the Redis hash of a recording."""
        get = {k.decode(): v.decode() for k, v in raw.items()}
        return cls(
            id=get["id"],
            device=get["device"],
            state=get["state"],
            decoder=get["decoder"],
            options=json.loads(get["options"]),
            max_frames=int(get["max_frames"]),
            max_samples=int(get.get("max_samples", MAX_RECORDING_SAMPLES)),
            frames=int(get.get("frames", "0")),
            started_ns=int(get.get("started_ns", "0")),
            stopped_ns=int(get["stopped_ns"]) if get.get("stopped_ns") else None,
            reason=get.get("reason") or None,
            keyframes=[int(i) for i in get.get("keyframes", "").split(",") if i],
            params=get.get("params", ""),
            shape=get.get("shape", ""),
            first_sequence=int(get["first_sequence"]) if get.get("first_sequence") else None,
            last_sequence=int(get["last_sequence"]) if get.get("last_sequence") else None,
            last_ts_ns=int(get["last_ts_ns"]) if get.get("last_ts_ns") else None,
            camera_steps=int(get.get("camera_steps", "0")),
            camera_span_ns=int(get.get("camera_span_ns", "0")),
            last_entry=get.get("last_entry") or None,
            start_entry=get.get("start_entry") or None,
            stop_entry=get.get("stop_entry") or None,
            frames_lost=int(get.get("frames_lost", "0")),
            frames_failed=int(get.get("frames_failed", "0")),
            frames_skipped=int(get.get("frames_skipped", "0")),
            failed_error=get.get("failed_error") or None,
            job=get.get("job") or None,
            error=get.get("error") or None,
        )

    def takes(self, entry_id: str) -> bool:
        """Whether the frame of stream entry ``entry_id`` belongs to the recording: sent
        after its start and, once stopping, at or before its stop (the newest entries then),
        however late the worker handles it."""
        if self.state not in ACTIVE_STATES:
            return False
        order = entry_order(entry_id)
        if self.start_entry is not None and order <= entry_order(self.start_entry):
            return False
        if self.state == "stopping":
            return self.stop_entry is not None and order <= entry_order(self.stop_entry)
        return True

    def wants(self, entry_id: str) -> bool:
        """Whether the frame of stream entry ``entry_id`` belongs to the recording and is
        not recorded yet (after ``last_entry``: a redelivery is not recorded twice)."""
        if not self.takes(entry_id):
            return False
        return self.last_entry is None or entry_order(entry_id) > entry_order(self.last_entry)

    def camera_fps(self) -> float | None:
        """The camera's frame rate over the recording (frames per s, 4 significant
        digits): its sequence steps between consecutive recorded frames (dropped frames
        count) over the device clock's time between them, leaving out steps across a
        discontinuity (a reconnect, a camera restart). None before two frames have
        measured it."""
        if self.camera_steps <= 0 or self.camera_span_ns <= 0:
            return None
        return float(f"{self.camera_steps * 1e9 / self.camera_span_ns:.4g}")

    def video_fps(self) -> float | None:
        """The rate its video plays at when the start named no ``fps`` (frames per s):
        :meth:`camera_fps` within :data:`FPS_RANGE`, the rates a video plays at."""
        fps = self.camera_fps()
        return None if fps is None else min(max(fps, FPS_RANGE[0]), FPS_RANGE[1])

    def view(self) -> dict[str, Any]:
        """The recording as JSON for the API (frame codes and stream cursors left out)."""
        return {
            "id": self.id,
            "device": self.device,
            "state": self.state,
            "frames": self.frames,
            "frames_lost": self.frames_lost,
            "frames_failed": self.frames_failed,
            "frames_skipped": self.frames_skipped,
            "max_frames": self.max_frames,
            "max_samples": self.max_samples,
            "decoder": self.decoder,
            "options": self.options,
            "keyframes": self.keyframes,
            "first_sequence": self.first_sequence,
            "last_sequence": self.last_sequence,
            "camera_fps": self.camera_fps(),
            "started_ns": self.started_ns,
            "stopped_ns": self.stopped_ns,
            "reason": self.reason,
            "job": self.job,
            "job_url": f"/v1/jobs/{self.job}" if self.job else None,
            "error": self.error,
        }


def recording_folder(recording_id: str) -> str:
    """Result-store folder of a recording's frames."""
    return f"recordings/{recording_id}"


def frame_key(recording_id: str, index: int) -> str:
    """Result-store key of a recorded frame's codes (.npy)."""
    return f"{recording_folder(recording_id)}/{index:06d}.npy"


def active_recording_folders(client: redis.Redis) -> list[str]:
    """Result-store folders of the recordings still collecting frames or waiting for
    their video job: their frames exist nowhere else, so no retention purges them."""
    devices = sorted(device.decode() for device in client.smembers(DEVICES_SET))
    pipe = client.pipeline(transaction=False)
    for device in devices:
        pipe.hmget(recording_key(device), "id", "state")
    return [
        recording_folder(recording_id.decode())
        for recording_id, state in pipe.execute()
        if recording_id and state and state.decode() in ACTIVE_STATES
    ]


def load_recording(client: redis.Redis, device: str) -> Recording | None:
    """The device's current or last recording; None if it never recorded."""
    raw = client.hgetall(recording_key(device))
    return Recording.from_hash(raw) if raw else None


def check_recordable(
    device: str, decoder: str, options: dict[str, Any], params: SensorParams,
    shape: tuple[int, ...], seen: str, *, max_samples: int,
) -> None:
    """Refuse a recording (``decoder``, video ``options``, at most ``max_samples`` code
    values) whose video job could never be made from the device's frames: codes of
    ``shape`` (H x W[x C], px) with ``params``, as ``seen`` says (its newest frame, its
    first recorded frame). The checks are those a video job gets on ``POST /v1/videos``,
    and that one frame fits ``max_samples``."""
    try:
        check_decoder_supports(decoder, params)
        check_frame_size(video_options(decoder, options)[1], (1, *shape))
        _check_frame_samples(shape, max_samples)
    except InvalidInputError as exc:
        raise InvalidInputError(
            f"device {device!r} sends {params.encoding} frames of {shape[0]} x {shape[1]} px "
            f"({seen}), which this recording cannot make into a video: {exc.message}"
        ) from None


def _check_frame_samples(shape: tuple[int, ...], max_samples: int) -> None:
    """Refuse frames of ``shape`` of which not one fits a recording of ``max_samples``
    code values (the server's ``MCAM_MAX_VIDEO_SAMPLES``)."""
    samples = int(np.prod(shape))
    if samples > max_samples:
        raise InvalidInputError(
            f"one frame holds {samples} code values, more than the recording's limit of "
            f"{max_samples}; have the camera send smaller frames, or raise the limit "
            "(MCAM_MAX_VIDEO_SAMPLES)"
        )


def reported_frames(
    client: redis.Redis, device: str
) -> tuple[SensorParams, tuple[int, int]] | None:
    """The sensor parameters and size (H, W px) of the device's newest frame, as its
    daemon reports them in its health ``settings``; None before any frame, or when the
    daemon reports parameters its frames are refused for (its frames then record none)."""
    settings = json.loads(client.hget(health_key(device), "settings") or "{}")
    if not {"encoding", "alpha", "bits", "height", "width"} <= settings.keys():
        return None
    try:
        params = SensorParams.parse(
            {name: settings[name] for name in ("encoding", "alpha", "bits")}
        )
    except InvalidInputError:
        return None
    return params, (int(settings["height"]), int(settings["width"]))


def recording_codes_bytes(
    max_frames: int, max_samples: int, reported: tuple[SensorParams, tuple[int, int]] | None
) -> int:
    """Most bytes of codes a recording's video job holds: ``max_frames`` frames of the
    device's newest frame (``reported``: its parameters and size, H x W px), at most
    ``max_samples`` code values; before any frame, ``max_samples`` of 2 bytes."""
    if reported is None:
        return 2 * max_samples
    params, (height, width) = reported
    return np.dtype(params.code_dtype).itemsize * min(max_frames * height * width, max_samples)


def check_room(client: redis.Redis, codes_bytes: int) -> None:
    """Refuse (:class:`StoreFullError`) a recording whose video job, of ``codes_bytes``
    bytes of codes, Redis could not take now (:func:`submit_room`): it is at its
    ``maxmemory`` (the camera's frames and the recording's progress are refused too) or
    has less free below it. Started anyway, it recorded nothing and answered 201."""
    free = free_memory(client.info("memory"))
    needed = submit_room(codes_bytes)
    if free is None or free >= needed:
        return
    if free < 0:
        trouble, fewer = "is full (at its maxmemory) and refuses writes", ""
    else:
        trouble = (
            f"has {free} bytes free below its maxmemory, less than this recording's video "
            f"needs there ({needed} bytes for up to {codes_bytes} bytes of codes)"
        )
        fewer = "record fewer frames (max_frames), "
    raise StoreFullError(
        f"the job store (Redis) {trouble}: no recording was started; {fewer}retry once "
        "queued jobs have finished and finished jobs' records expired, or raise "
        "MCAM_REDIS_MAXMEMORY (an external Redis: its maxmemory)"
    )


def start_recording(
    client: redis.Redis,
    device: str,
    *,
    decoder: str,
    options: dict[str, Any],
    max_frames: int,
    max_samples: int = MAX_RECORDING_SAMPLES,
) -> Recording | None:
    """Start a recording (options: those of a video job; ``max_samples``: most code
    values of the video); None if one is already active. Refused when the device's newest
    frame shows its video job could never be made (:func:`check_recordable`), and with
    :class:`DeviceNotFoundError` when the device is not registered (checked in the same
    step as the write: a forget that came first leaves no record behind), and with
    :class:`StoreFullError` when Redis has no room for its video (:func:`check_room`)."""
    if max_frames < 1:
        raise InvalidInputError(f"max_frames must be at least 1, got {max_frames}")
    if not 1 <= max_samples <= MAX_RECORDING_SAMPLES * 2:
        raise InvalidInputError(
            f"max_samples must be within [1, {MAX_RECORDING_SAMPLES * 2}], got {max_samples}"
        )
    reported = reported_frames(client, device)
    if reported is not None:
        check_recordable(
            device, decoder, options, *reported, "its newest frame", max_samples=max_samples
        )
    check_room(client, recording_codes_bytes(max_frames, max_samples, reported))
    fields = {
        "id": uuid.uuid4().hex,
        "device": device,
        "state": "recording",
        "decoder": decoder,
        "options": json.dumps(options),
        "max_frames": str(max_frames),
        "max_samples": str(max_samples),
        "frames": "0",
        "started_ns": str(time.time_ns()),
    }
    args = [device, *(item for pair in fields.items() for item in pair)]
    started = client.register_script(_START)(
        keys=[recording_key(device), DEVICES_SET, frame_stream(device)], args=args
    )
    if started == -1:
        raise DeviceNotFoundError(device)
    if not started:
        return None
    return load_recording(client, device)


def request_stop(client: redis.Redis, device: str) -> Recording | None:
    """Ask the worker to end the device's recording; returns the record as the stop left
    it, read in the same step (None: never any). A start right after the stop is not
    taken for the recording it stopped (read apart, the stop answered with it, still
    recording)."""
    raw = client.register_script(_STOP)(
        keys=[recording_key(device), frame_stream(device)], args=[time.time_ns()]
    )
    return Recording.from_hash(dict(zip(raw[::2], raw[1::2], strict=True))) if raw else None
