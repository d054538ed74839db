"""Forgetting a device: every Redis key of a camera whose daemon has gone, removed at once.

A daemon registers its device in ``devices`` with its first health write or frame, and
nothing else takes it out, so a camera retired for good stayed in ``GET /v1/devices``.
:func:`forget_device` removes it with its health, control stream and cursor, events,
newest-result pointer, sequence record, lease and recording record, and its series of
the device-labelled counters (:func:`worker.metrics.forget_label`), but only while no
daemon reports for it, no recording is running and (unless the caller says to discard
them) no frame waits to be decoded. Reconstructions already stored stay in the result
store until their retention ends. A daemon that comes back registers the device again.
"""

from __future__ import annotations

import time

import redis

from device.health import ENDED_STATES
from models.errors import McamError
from worker.metrics import forget_label
from worker.redis_keys import (
    DEVICES_SET,
    control_cursor_key,
    control_stream,
    daemon_key,
    events_stream,
    frame_stream,
    health_key,
    last_sequence_key,
    latest_key,
    lease_key,
    recording_key,
)

#: Recording states in which frames still go into a recording.
_ACTIVE_RECORDING = (b"recording", b"stopping")


class DeviceBusyError(McamError):
    """The device cannot be forgotten now (a live daemon, a recording, undecoded frames)."""

    code = "device_busy"
    http_status = 409


class DeviceNotFoundError(McamError):
    """No daemon has registered the device, or it was forgotten."""

    code = "not_found"
    http_status = 404

    def __init__(self, device: str) -> None:
        super().__init__(f"no device {device!r}; GET /v1/devices lists them")


def device_keys(device: str) -> list[str]:
    """Every per-device key, in the order :func:`forget_device` deletes them."""
    return [
        health_key(device), control_stream(device), control_cursor_key(device),
        events_stream(device), latest_key(device), last_sequence_key(device),
        lease_key(device), recording_key(device), frame_stream(device), daemon_key(device),
    ]  # fmt: skip


def stopped_recording_text(device: str, recording: str) -> str:
    """Why device ``device`` is still busy with its recording ``recording`` (id) after a
    stop: the worker has not made the video yet (another stop changes nothing)."""
    return (
        f"device {device!r}'s recording {recording} was stopped and waits for the worker "
        "to make its video from the frames sent before the stop (is a worker running, and "
        "keeping up with the camera?)"
    )


def _refusal(pipe: redis.client.Pipeline, device: str, silent_after_s: float,
             waiting: int, discard_frames: bool) -> str | None:
    """Why ``device`` must stay (read inside the WATCH; ``waiting``: its undecoded
    frames), or None."""
    updated, state = pipe.hmget(health_key(device), "updated_ns", "state")  # one snapshot
    ended = state is not None and state.decode() in ENDED_STATES  # its daemon said so
    if not ended and updated is not None and time.time_ns() - int(updated) < silent_after_s * 1e9:
        return (f"the daemon of device {device!r} reported {silent_after_s:g} s ago or less; "
                "stop it (mcam device ... ends with Ctrl-C or SIGTERM) and retry")
    recording, state = pipe.hmget(recording_key(device), "id", "state")
    if state == b"stopping":
        return (f"{stopped_recording_text(device, recording.decode())}; retry once GET "
                f"/v1/devices/{device}/recordings shows it submitted or failed")
    if state in _ACTIVE_RECORDING:
        return (f"device {device!r} is recording; stop it with POST "
                f"/v1/devices/{device}/recordings {{\"action\": \"stop\"}} and retry")
    if waiting and not discard_frames:
        return (f"{waiting} frame(s) of device {device!r} are not decoded yet; wait for a "
                "worker to decode them, or pass discard_frames=true to drop them")
    return None


def forget_device(client: redis.Redis, device: str, *, silent_after_s: float,
                  discard_frames: bool = False) -> int:
    """Remove ``device`` and its keys atomically; returns how many undecoded frames went
    with it. Raises :class:`DeviceBusyError` when its daemon reported within the last
    ``silent_after_s`` seconds (unless it said it ended: stopped or crashed), while it
    records, or while frames wait and ``discard_frames`` is false, and
    :class:`DeviceNotFoundError` when it is not registered (never, or another caller
    forgot it first). Retried if a daemon or worker writes meanwhile."""
    keys = device_keys(device)
    while True:
        with client.pipeline() as pipe:
            try:
                pipe.watch(DEVICES_SET, *keys)
                if not pipe.sismember(DEVICES_SET, device):
                    raise DeviceNotFoundError(device)
                waiting = int(pipe.xlen(frame_stream(device)))
                refusal = _refusal(pipe, device, silent_after_s, waiting, discard_frames)
                if refusal is not None:
                    raise DeviceBusyError(refusal)
                pipe.multi()
                pipe.srem(DEVICES_SET, device)
                pipe.delete(*keys)
                forget_label(pipe, "device", device)
                pipe.execute()
                return waiting
            except redis.WatchError:
                continue
