"""The worker's side of live recordings: frames added to the device's recording, its video
job queued.

Usage (worker: the device stream's single owner, frames in sequence order)::

    recorder = Recorder(client, store, max_deliveries=3)
    recorder.add_frame(message, entry_id)   # each reconstructed frame, before it is committed
    recorder.finish_if_due("cam1")          # every poll, frames or not

The record, its states, and its start and stop are in :mod:`worker.recordings`.

A device's frame stream keeps its newest ``MCAM_FRAMES_MAXLEN`` frames: frames of the
recording's window that it drops before any worker read them (no worker running, or one
far behind) count in ``frames_lost`` (:func:`worker.queue.publish_frame`), and so do those
it drops while a worker that stopped before recording them held them
(:meth:`Recorder.count_lost`, when the next owner finds them gone): a recording
that ends with no frame fails saying how many were lost and what to do, and the video
job of one that lost some carries that as a warning. So do frames of the recording that
the worker gave up on (they could not be reconstructed: a ``failed`` event),
``frames_failed``, with the last one's error (:meth:`Recorder.count_failed`). Frames
that never reached the stream (lost on the camera link: corrupt, truncated or undelivered
packets, a disconnect; or dropped by the device daemon) show as steps of the camera's
sequence numbers between recorded frames: those steps count in ``frames_skipped``, and
the video job warns of the frames skipped beyond those lost and failed. Frames with an
odd side are padded to even ones in the MP4 videos, which the job's warnings say too, as
a job of ``POST /v1/videos`` does (:func:`worker.video_jobs.video_warnings`).
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np
import redis

from device.health import MAX_MISSING_PER_GAP
from models.errors import InvalidInputError, McamError
from models.formation import SensorParams
from models.frames import encode_frame
from worker.frame_message import FrameMessage
from worker.queue import JobQueue
from worker.recording_texts import (
    camera_rate_text,
    frames_change_text,
    missing_frames,
    no_frames_reason,
    samples_limit_text,
)
from worker.recordings import (
    ACTIVE_STATES,
    Recording,
    check_recordable,
    frame_key,
    load_recording,
    recording_folder,
)
from worker.redis_keys import frame_stream, recording_key
from worker.result_store import ResultStore
from worker.video_jobs import video_options, video_warnings

#: Bound of the jobs stream for recorded videos: a recording already accepted is not
#: lost to a full queue (its frames exist nowhere else).
RECORDING_QUEUE_MAXLEN = 1 << 30

# ARGV: the recording's id, the states it may be in (space-separated; '' any), the frames
# it must have ('' any), then field, value pairs.
_UPDATE = """
if redis.call('HGET', KEYS[1], 'id') ~= ARGV[1] then return 0 end
local state = redis.call('HGET', KEYS[1], 'state')
if ARGV[2] ~= '' and not string.find(' ' .. ARGV[2] .. ' ', ' ' .. state .. ' ', 1, true) then
  return 0
end
if ARGV[3] ~= '' and redis.call('HGET', KEYS[1], 'frames') ~= ARGV[3] then return 0 end
local fields = {}
for i = 4, #ARGV do fields[#fields + 1] = ARGV[i] end
redis.call('HSET', KEYS[1], unpack(fields))
return 1
"""


# One more frame lost to the recording of KEYS[1] if it is still recording ARGV[1] (its
# id): an increment, as the device daemon's publish counts there too.
_COUNT_LOST = """
local r = redis.call('HMGET', KEYS[1], 'id', 'state')
if r[1] ~= ARGV[1] or (r[2] ~= 'recording' and r[2] ~= 'stopping') then return 0 end
return redis.call('HINCRBY', KEYS[1], 'frames_lost', 1)
"""

# One more frame of the recording of KEYS[1] (id ARGV[1]) that failed to decode: stream
# entry ARGV[2], whose error is ARGV[3]. Its redelivery (the ack did not happen) is not
# counted again.
_COUNT_FAILED = """
local r = redis.call('HMGET', KEYS[1], 'id', 'state', 'failed_entry')
if r[1] ~= ARGV[1] or (r[2] ~= 'recording' and r[2] ~= 'stopping') then return 0 end
if r[3] == ARGV[2] then return 0 end
redis.call('HSET', KEYS[1], 'failed_entry', ARGV[2], 'failed_error', ARGV[3])
return redis.call('HINCRBY', KEYS[1], 'frames_failed', 1)
"""


class Recorder:
    """The worker's side: appends frames to active recordings and queues their video jobs."""

    def __init__(self, client: redis.Redis, store: ResultStore, *, max_deliveries: int) -> None:
        self.client = client
        self.store = store
        self.queue = JobQueue(
            client, maxlen=RECORDING_QUEUE_MAXLEN, max_deliveries=max_deliveries,
            claim_idle_ms=1,
        )
        self._update = client.register_script(_UPDATE)
        self._count_lost = client.register_script(_COUNT_LOST)
        self._count_failed = client.register_script(_COUNT_FAILED)

    def _set(
        self, recording: Recording, fields: dict[str, Any], *,
        states: tuple[str, ...] = ACTIVE_STATES, frames: int | None = None,
    ) -> bool:
        """Write ``fields`` if the record is still this recording (same id), in one of
        ``states``, with ``frames`` frames when given; returns whether it wrote. An ended
        recording is never written again: a second owner of the device (the first
        stalled past its lease) finishing it too would fail it over its queued job."""
        args: list[Any] = [recording.id, " ".join(states), "" if frames is None else frames]
        args += [item for pair in fields.items() for item in pair]
        return bool(self._update(keys=[recording_key(recording.device)], args=args))

    def add_frame(self, message: FrameMessage, entry_id: str) -> None:
        """Record a reconstructed frame if it belongs to the device's recording."""
        recording = load_recording(self.client, message.device)
        if recording is None or not recording.wants(entry_id):
            return
        if recording.frames >= recording.max_frames:
            self._finish(recording, "max_frames")  # Redis refused its job at its last frame
            return
        index = recording.frames
        shape = ",".join(map(str, message.codes.shape))
        update: dict[str, Any] = {
            "last_entry": entry_id,
            "last_sequence": message.sequence,
            "last_ts_ns": message.timestamp_ns,
            **camera_timing(recording, message),
            **skipped_frames(recording, message),
        }
        if index == 0:
            if not self._recordable(recording, message):
                return
            update |= {
                "params": message.params.model_dump_json(),
                "shape": shape,
                "first_sequence": message.sequence,
            }
        elif change := frames_change_text(recording, message):
            self._finish(recording, "params_changed", change)
            return
        if (index + 1) * message.codes.size > recording.max_samples:
            self._finish(recording, "max_samples", samples_limit_text(recording, message))
            return
        if index and (message.discont or message.sequence != (recording.last_sequence or 0) + 1):
            update["keyframes"] = ",".join(map(str, [*recording.keyframes, index]))
        self.store.write(frame_key(recording.id, index), encode_frame(message.codes, None, "npy"))
        update["frames"] = index + 1
        if not self._set(recording, update, frames=index):
            return
        if index + 1 >= recording.max_frames:
            self._finish(load_recording(self.client, message.device) or recording, "max_frames")

    def count_lost(self, device: str, entry_id: str) -> None:
        """Count in the device's recording (``frames_lost``) the frame of stream entry
        ``entry_id`` if it belongs to it and is not recorded: the full stream dropped it
        while a worker held it unrecorded (one that stopped after reading it)."""
        recording = load_recording(self.client, device)
        if recording is not None and recording.wants(entry_id):
            self._count_lost(keys=[recording_key(device)], args=[recording.id])

    def count_failed(self, device: str, entry_id: str, error: str) -> None:
        """Count in the device's recording (``frames_failed``, with ``error``, the
        client's words for why) the frame of stream entry ``entry_id`` if it belongs to it
        and the worker gave up on it (it could not be reconstructed): it is left out."""
        recording = load_recording(self.client, device)
        if recording is not None and recording.wants(entry_id):
            self._count_failed(keys=[recording_key(device)], args=[recording.id, entry_id, error])

    def _recordable(self, recording: Recording, message: FrameMessage) -> bool:
        """Whether the recording's video job can be made from frames like ``message``'s
        (its first); if not, the recording ends failed with the reason."""
        try:
            check_recordable(
                recording.device, recording.decoder, recording.options, message.params,
                message.codes.shape, "its first recorded frame",
                max_samples=recording.max_samples,
            )
        except InvalidInputError as exc:
            self._fail(recording, "frames_refused", exc.message)
            return False
        return True

    def finish_if_due(self, device: str) -> None:
        """Queue the video job of a recording the API asked to stop, once every frame sent
        before the stop has been handled (none at or before its ``stop_entry`` is left on
        the stream: the worker deletes each entry it is done with), or of one holding its
        ``max_frames`` frames whose job Redis refused when the last of them came (full or
        unreachable: that frame, retried, is not recorded twice, so it ends here)."""
        state, frames, max_frames = self.client.hmget(
            recording_key(device), "state", "frames", "max_frames"
        )
        full = bool(frames and max_frames and int(frames) >= int(max_frames))
        if state not in (b"recording", b"stopping") or (state == b"recording" and not full):
            return
        recording = load_recording(self.client, device)
        if recording is None or recording.state not in ACTIVE_STATES:
            return
        if full:
            self._finish(recording, "max_frames")
        elif not self._frames_left(recording):
            self._finish(recording, recording.reason or "requested")

    def _frames_left(self, recording: Recording) -> bool:
        """Whether frames sent before the recording's stop still wait on the stream."""
        if recording.stop_entry is None:
            return False
        return bool(self.client.xrange(
            frame_stream(recording.device), "-", recording.stop_entry, count=1
        ))

    def _finish(self, recording: Recording, reason: str, ended: str | None = None) -> None:
        """Assemble the recorded frames (T x H x W codes), queue the video job, note its id;
        ``ended``: why the recording ended before its stop, for the job's warnings."""
        try:
            job = self._submit(recording, reason, ended)
        except McamError as exc:
            self._fail(recording, reason, exc.message)
        else:
            self._set(recording, {**_ended(recording, reason), "state": "submitted", "job": job})
        for key in self.store.keys(recording_folder(recording.id)):
            self.store.delete(key)

    def _fail(self, recording: Recording, reason: str, error: str) -> None:
        """End the recording as failed, ``error`` saying why (no video job comes)."""
        self._set(recording, {**_ended(recording, reason), "state": "failed", "error": error})

    def _submit(self, recording: Recording, reason: str, ended: str | None) -> str:
        missing = missing_frames(recording)
        if recording.frames == 0 and missing:
            raise InvalidInputError(f"no frames were recorded: {'; '.join(missing)}")
        if recording.frames == 0:
            raise InvalidInputError(
                f"no frames were recorded: {no_frames_reason(self.client, recording)}"
            )
        codes = np.stack(
            [np.load(self.store.existing_path(frame_key(recording.id, i)))
             for i in range(recording.frames)]
        )
        options = {**recording.options, "keyframes": recording.keyframes}
        fps = recording.video_fps()
        if "fps" not in options and fps is not None:
            options["fps"] = fps
        params = SensorParams.model_validate_json(recording.params)
        # The recording's id names its job: if noting the job below fails (Redis down),
        # the next try finds the job queued instead of queueing it twice.
        outputs = video_options(recording.decoder, options)[1]
        return self.queue.submit(
            "video", codes, params, recording.decoder, options, job_id=recording.id,
            warnings=video_warnings([*missing, *_notes(ended, camera_rate_text(recording))],
                                    outputs, codes.shape),
        ).id


def camera_timing(recording: Recording, message: FrameMessage) -> dict[str, int]:
    """The recording's camera steps and device time (ns) with ``message``, the next
    recorded frame, counted in: nothing when it follows a discontinuity, a bracketed
    capture (its packets, one scene instant, took sequence numbers but no frame periods)
    or its sequence number or timestamp does not advance (a camera restart)."""
    if recording.frames == 0 or message.discont or message.bracketed:
        return {}
    if recording.last_sequence is None or recording.last_ts_ns is None:
        return {}
    steps = message.sequence - recording.last_sequence
    span_ns = message.timestamp_ns - recording.last_ts_ns
    if steps <= 0 or span_ns <= 0:
        return {}
    return {
        "camera_steps": recording.camera_steps + steps,
        "camera_span_ns": recording.camera_span_ns + span_ns,
    }


def skipped_frames(recording: Recording, message: FrameMessage) -> dict[str, int]:
    """The recording's ``frames_skipped`` with ``message``, the next recorded frame,
    counted in: the sequence numbers between the last recorded frame's and its own, less
    those a bracketed capture's packets took (never streamed, no frames lost); nothing
    for its first frame, a step back (a camera restart) or a jump beyond
    :data:`MAX_MISSING_PER_GAP` (a counter that reset or was corrupted)."""
    if recording.frames == 0 or recording.last_sequence is None:
        return {}
    skipped = message.sequence - recording.last_sequence - 1 - message.bracketed
    if not 0 < skipped <= MAX_MISSING_PER_GAP:
        return {}
    return {"frames_skipped": recording.frames_skipped + skipped}


def _notes(*texts: str | None) -> list[str]:
    """The ``texts`` given (warnings of a video job), in order."""
    return [text for text in texts if text]


def _ended(recording: Recording, reason: str) -> dict[str, Any]:
    """The fields of a recording that ends for ``reason`` (its stop time: when the API
    asked, else now; ns since the epoch)."""
    return {"reason": reason, "stopped_ns": recording.stopped_ns or time.time_ns()}
