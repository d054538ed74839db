"""What a live recording misses, and why, in the client's words: the error of a recording
that got no frame (its daemon crashed, its port does not open, none came between the start
and the stop), and the warnings of a video job that lacks frames (lost to the device's full
frame stream, failed to decode, or never reached the stream; after the recording ended by
itself on a change of the camera's settings or at the server's sample limit) or plays
slower than its camera. See :mod:`worker.recorder`, which ends recordings with them."""

from __future__ import annotations

import time

import redis

from device.health import crashed_daemon_text
from models.formation import SensorParams
from worker.frame_message import FrameMessage
from worker.recordings import Recording
from worker.redis_keys import health_key
from worker.video_output import FPS_RANGE

#: How far above the fastest video rate a camera's measured rate may be before its
#: recording's video warns that it plays slower than the camera (a clock's jitter).
RATE_TOLERANCE = 1.01


def no_frames_reason(client: redis.Redis, recording: Recording) -> str:
    """Why ``recording`` got no frame, none lost or failed: its daemon crashed (its
    health's ``state`` and ``crash``) or cannot open the camera's port (``port_error``),
    or (:func:`_no_frame_sent_text`) no frame reached the stream between its start and
    stop."""
    device = recording.device
    state, crash, port_error = client.hmget(health_key(device), "state", "crash", "port_error")
    if state == b"crashed":
        return (
            f"{crashed_daemon_text(device, (crash or b'').decode())}: restart mcam device "
            "(its log has the traceback: please report it)"
        )
    if port_error:
        return (
            f"the daemon of device {device!r} cannot open its camera's port "
            f"({port_error.decode()})"
        )
    return _no_frame_sent_text(recording)


def _no_frame_sent_text(recording: Recording) -> str:
    """That no frame reached the device's stream between the recording's start and stop
    (a worker finished it, so none waited unread), how long that was (s), and what to do:
    record for longer than one of the camera's frames, or get it streaming."""
    device = recording.device
    window_s = max((recording.stopped_ns or time.time_ns()) - recording.started_ns, 0) / 1e9
    return (
        f"no frame reached device {device!r}'s stream in the {window_s:.3g} s between the "
        "start and the stop: record for longer than one frame of its camera (GET "
        f"/v1/devices/{device} shows its fps), and check there that it is streaming (state "
        "connected, fps above 0)"
    )


def missing_frames(recording: Recording) -> list[str]:
    """What the recording misses, and why: frames the device stream dropped before a
    worker read them, frames that failed to decode, frames that never reached the stream
    (the video's warnings)."""
    missing = [frames_lost_text(recording)] if recording.frames_lost else []
    if recording.frames_failed:
        frames = _frames_sent(recording.frames_failed)
        missing.append(
            f"{frames} failed to decode and {'is' if recording.frames_failed == 1 else 'are'} "
            f"left out (the last: {recording.failed_error}); GET /v1/devices/"
            f"{recording.device}/events lists each failed frame"
        )
    unexplained = recording.frames_skipped - recording.frames_lost - recording.frames_failed
    if unexplained > 0:
        missing.append(frames_skipped_text(recording, unexplained))
    return missing


def frames_skipped_text(recording: Recording, count: int) -> str:
    """What ``count`` frames skipped between recorded frames, beyond those the stream
    dropped or that failed to decode, mean to ``recording``, and where to look. "At
    least" once some were lost or failed: those may lie before the first or after the
    last recorded frame, outside the skipped steps."""
    bound = "at least " if recording.frames_lost or recording.frames_failed else ""
    frames = "frame" if count == 1 else "frames"
    return (
        f"{bound}{count} {frames} the camera numbered between the recording's first and "
        f"last frame never reached the device's frame stream and {'is' if count == 1 else 'are'} "
        "missing from the video (lost on the camera link: corrupt, truncated or undelivered "
        "packets, a disconnect; dropped by the device daemon; or sent while it was not "
        "running): GET /v1/devices/"
        f"{recording.device} counts them by cause (frames_missing, dropped_*); check the "
        "camera's cable and the daemon's log"
    )


def _frames_sent(count: int) -> str:
    """``count`` frames the camera sent while recording, as words."""
    if count == 1:
        return "1 frame the camera sent between the start and the stop"
    return f"{count} frames the camera sent between the start and the stop"


def frames_lost_text(recording: Recording) -> str:
    """What losing its ``frames_lost`` frames to its device's full frame stream means to
    ``recording``, and what to do."""
    lost = recording.frames_lost
    return (
        f"{_frames_sent(lost)} {'was' if lost == 1 else 'were'} dropped from the device's "
        "frame stream before a worker read them (it keeps the newest MCAM_FRAMES_MAXLEN "
        f"frames; stream_full in GET /v1/devices/{recording.device}); keep a worker running "
        "while recording, or raise MCAM_FRAMES_MAXLEN on the device daemon"
    )


def frames_change_text(recording: Recording, message: FrameMessage) -> str | None:
    """What changed in ``message``, the frame after the recording's last, from its frames
    (their size, H x W px, or sensor parameters other than the noise seed), which ends
    the recording there, and what to do: the warning its video job carries. None when
    nothing changed."""
    shape = ",".join(map(str, message.codes.shape))
    if shape != recording.shape:
        change = (
            f"frame size changed from {recording.shape.replace(',', ' x ')} to "
            f"{shape.replace(',', ' x ')}"
        )
    else:
        params = SensorParams.model_validate_json(recording.params)
        changed = params.differences(message.params)
        if not changed:
            return None
        change = ", ".join(
            f"{name} changed from {getattr(params, name)} to {getattr(message.params, name)}"
            for name in changed
        )
    return _ended_early_text(
        recording, message, f", whose {change} (one video keeps one sensor setting)"
    )


def samples_limit_text(recording: Recording, message: FrameMessage) -> str:
    """That ``message``, the frame after the recording's last, would take its video past
    its ``max_samples`` code values (the server's ``MCAM_MAX_VIDEO_SAMPLES``), which ends
    the recording there, and what to do: the warning its video job carries."""
    return _ended_early_text(
        recording, message,
        f": with it the video would hold more than the server's limit of "
        f"{recording.max_samples} code values (MCAM_MAX_VIDEO_SAMPLES; {recording.frames} "
        "frames of this size fit; record fewer frames at a time with max_frames, or raise "
        "the limit)",
    )


def _ended_early_text(recording: Recording, message: FrameMessage, why: str) -> str:
    """That the recording ended before ``message``, the camera's next frame, ``why``, and
    that a new recording records the frames from then on."""
    return (
        f"the recording ended by itself before the camera's frame {message.sequence}{why}: "
        "frames from then on are not in this video; start a new recording (POST "
        f"/v1/devices/{recording.device}/recordings action=start) to record them"
    )


def camera_rate_text(recording: Recording) -> str | None:
    """That the camera ran faster than the fastest rate a video plays at
    (:data:`FPS_RANGE`), so the video of a recording whose start named no ``fps`` plays
    slower than the camera, and what to do: the warning its video job carries. None
    otherwise."""
    fps = recording.camera_fps()
    fastest = FPS_RANGE[1]
    if "fps" in recording.options or fps is None or fps <= fastest * RATE_TOLERANCE:
        return None
    return (
        f"the camera ran at {fps:g} frames/s, faster than the {fastest:g} frames/s a "
        f"video plays at: this video plays at {fastest:g} frames/s, {fps / fastest:.3g}x "
        "slower than the camera; to choose its rate, give fps with action=start"
    )
