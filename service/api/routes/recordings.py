"""``/v1/devices/{id}/recordings``: record a live device stream into a video job.

``POST`` with ``action=start`` (and the video options of ``POST /v1/videos``, plus
``max_frames``) starts a recording; the worker that owns the device stream stores
each frame the camera sent from then on, until the stop. ``action=stop`` ends it: once
it has handled the frames sent before the stop, the worker queues the video job and the
answer is that job (202, or 200 with the finished job under ``Prefer: wait=N``; a
stop takes no other field: 422); its files come from ``GET /v1/videos/{job}/result``.
Fields come as JSON (``outputs`` also as a list of names), form fields or query
parameters. ``GET`` shows the current (or last) recording with its frame count. A
start is refused (422) when the device's newest frame shows that its video could never
be made (a decoder with no model for the frames' encoding, ``hdr10`` of frames under
64 px, a frame of more code values than the server's ``MCAM_MAX_VIDEO_SAMPLES``);
before any frame, the first one recorded is checked, and a refusal ends the recording
``failed`` with the reason (``GET``, and the stop's 409). See ``worker/recordings.py``.
"""

from __future__ import annotations

import time
from dataclasses import replace
from typing import Annotated, Any, Literal

from fastapi import APIRouter, Header, Request, Response
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from pydantic import Field, ValidationError
from starlette.concurrency import run_in_threadpool

from models.decoders.registry import resolve
from models.errors import InvalidInputError
from service.api.deps import ReadKey, StateDep, SubmitKey
from service.api.errors import ApiError
from service.api.media_types import media_type
from service.api.routes.devices import DEVICE_ERRORS, known_device
from service.api.routes.reconstructions import prefer_wait_s
from service.api.routes.videos import VideoOptionFields
from service.api.schemas import (
    SMALL_BODY_ERRORS,
    WRITE_REFUSED,
    JobAccepted,
    JobView,
    error_response,
    job_response,
)
from service.api.state import ServiceState
from worker.device_registry import stopped_recording_text
from worker.jobs import JobNotFoundError
from worker.recordings import (
    Recording,
    load_recording,
    request_stop,
    start_recording,
)
from worker.video_jobs import video_options

router = APIRouter(prefix="/v1/devices", tags=["recordings"])
#: How long a stop waits for the worker to queue the video job (s) before answering 202.
STOP_WAIT_S = 10.0
#: Most frames of a recording that names no ``max_frames`` (or the server's
#: ``MCAM_MAX_VIDEO_FRAMES``, if lower).
DEFAULT_MAX_FRAMES = 300
RECORDING_ERRORS = {
    **DEVICE_ERRORS,
    **SMALL_BODY_ERRORS,
    503: WRITE_REFUSED,
    409: error_response(
        "start: recording_running (one is running); stop: no_recording (none is running, "
        "or the last one's video job expired) or recording_failed (the worker could not "
        "make its video job)"
    ),
}


class RecordingFields(VideoOptionFields):
    """Fields of ``POST /v1/devices/{id}/recordings`` (video options apply to ``start``)."""

    action: Literal["start", "stop"] = Field(description="start or stop the recording")
    max_frames: int | None = Field(
        None, ge=1, lt=1 << 63,
        description=f"the recording stops by itself after these (default "
        f"{DEFAULT_MAX_FRAMES}, or the server's MCAM_MAX_VIDEO_FRAMES if lower)",
    )


#: A recording form names a handful of fields; Starlette's default allows 1000 and files.
MAX_FORM_FIELDS = 32


def _refuse_booleans(values: dict[str, Any]) -> None:
    """A JSON ``true`` for a number field is refused (pydantic would read it as 1)."""
    for name, value in values.items():
        field = RecordingFields.model_fields.get(name)
        if isinstance(value, bool) and field is not None and field.annotation is not bool:
            raise InvalidInputError(f"{name} must be a number, not {str(value).lower()}")


def _outputs_as_text(values: dict[str, Any]) -> None:
    """Take ``outputs`` given as the JSON list of names a recording's view shows them in
    (``["hdr10", "sdr"]``) as their comma-separated form (``hdr10,sdr``)."""
    outputs = values.get("outputs")
    if isinstance(outputs, list) and all(isinstance(name, str) for name in outputs):
        values["outputs"] = ",".join(outputs)


def _refuse_start_fields(fields: RecordingFields) -> None:
    """A stop takes no video options nor ``max_frames``: they were dropped unseen, the
    video made as its start asked."""
    given = sorted(fields.model_fields_set - {"action"})
    if given:
        raise InvalidInputError(
            f"a stop takes only action=stop, but {', '.join(given)} came with it: video "
            "options and max_frames go with action=start; send action=stop alone (the "
            "video is made as its start asked)"
        )


async def read_fields(request: Request) -> RecordingFields:
    """The fields from the query, updated by a JSON or form body (422 if bad)."""
    values: dict[str, Any] = dict(request.query_params)
    media = media_type(request)
    if media == "application/json":
        try:
            body = await request.json()
        except (ValueError, RecursionError):
            raise InvalidInputError("the JSON body is malformed; send an object") from None
        if not isinstance(body, dict):
            raise InvalidInputError("the JSON body must be an object, e.g. {\"action\": \"start\"}")
        values |= body
    elif media in ("application/x-www-form-urlencoded", "multipart/form-data"):
        async with request.form(max_files=0, max_fields=MAX_FORM_FIELDS) as form:
            values |= {name: value for name, value in form.items() if isinstance(value, str)}
    elif await request.body():
        raise InvalidInputError(
            f"the body came as {media or 'no content type'!r} and was not read: send a JSON "
            "object with the header 'Content-Type: application/json', or form fields"
        )
    _refuse_booleans(values)
    _outputs_as_text(values)
    try:
        return RecordingFields.model_validate(values)
    except ValidationError as exc:
        raise RequestValidationError(exc.errors()) from None


def _recording_response(recording: Recording, status: int) -> JSONResponse:
    return JSONResponse(
        recording.view(), status_code=status,
        headers={"Location": f"/v1/devices/{recording.device}/recordings"},
    )


def start(state: ServiceState, device: str, fields: RecordingFields) -> Response:
    """Check the options and write the recording's record (409 if one is running)."""
    limit = state.settings.max_video_frames
    max_frames = min(DEFAULT_MAX_FRAMES, limit) if fields.max_frames is None else fields.max_frames
    if max_frames > limit:
        raise InvalidInputError(
            f"max_frames {max_frames} is above this server's limit of {limit} frames; "
            f"ask for at most {limit}, or raise the limit (MCAM_MAX_VIDEO_FRAMES)"
        )
    decoder = fields.decoder or state.settings.default_decoder
    resolve(decoder)
    options = fields.video_job_options()
    if "fps" not in fields.model_fields_set:
        del options["fps"]  # the video plays at the camera's measured rate (camera_fps)
    video_options(decoder, options)
    recording = start_recording(
        state.client, device, decoder=decoder, options=options, max_frames=max_frames,
        max_samples=state.settings.max_video_samples,
    )
    if recording is None:
        raise ApiError(409, "recording_running", _running_message(state, device))
    return _recording_response(recording, 201)


def _running_message(state: ServiceState, device: str) -> str:
    """Why a start found the device's recording active, and what to do: stop it, or wait
    for the worker to make the video of one already stopped."""
    active = load_recording(state.client, device)
    if active is None or active.state != "stopping":
        return f"device {device!r} is already recording; stop it first (action=stop)"
    return (
        f"{stopped_recording_text(device, active.id)}; start again once GET "
        f"/v1/devices/{device}/recordings shows it submitted or failed"
    )


def _ended_and_replaced(state: ServiceState, recording: Recording) -> Recording:
    """``recording`` (stopping) once a newer recording or a forget has taken its record:
    it ended meanwhile, submitted if its video job (named by its id) exists, else failed."""
    try:
        state.queue.get(recording.id)
    except JobNotFoundError:
        return replace(recording, state="failed", error=(
            "the worker made no video job of it, and a newer recording has replaced its "
            "record (the reason went with it); start a new recording"
        ))
    return replace(recording, state="submitted", job=recording.id)


def _wait_for_job(state: ServiceState, device: str, recording: Recording) -> Recording:
    """The recording once the worker queued its job or failed (or as it is after a while).
    A newer recording in its place ended it between two looks: it is never taken for
    this one (the stop answered 202 with it, still recording)."""
    deadline = time.monotonic() + STOP_WAIT_S
    while (recording.state == "stopping" and time.monotonic() < deadline
           and not state.stopping.is_set()):
        time.sleep(0.05)
        latest = load_recording(state.client, device)
        if latest is None or latest.id != recording.id:
            return _ended_and_replaced(state, recording)
        recording = latest
    return recording


def stop(state: ServiceState, device: str, wait_s: float) -> Response:
    """End the recording and answer with its video job. The wait for the worker to queue
    the job holds a server thread, so it takes one of the ``Prefer: wait`` slots; with
    none free the recording is answered at once, still stopping (45 stops waiting on a
    stalled worker made every other request wait 9 s)."""
    recording = request_stop(state.client, device)
    if recording is None:
        raise ApiError(
            409, "no_recording", f"device {device!r} is not recording; start one (action=start)"
        )
    if state.wait_slots.take():
        try:
            recording = _wait_for_job(state, device, recording)
        finally:
            state.wait_slots.release()
    if recording.state == "failed":
        raise ApiError(409, "recording_failed", f"recording {recording.id} failed: "
                       f"{recording.error}")
    if recording.job is None:
        return _recording_response(recording, 202)
    try:
        job = state.queue.get(recording.job)
    except JobNotFoundError:
        raise ApiError(409, "no_recording", (
            f"device {device!r} is not recording: its last recording ended "
            f"({recording.reason}) and its video job {recording.job} has expired "
            "(MCAM_RESULT_RETENTION_S); start a new one (action=start)"
        )) from None
    return job_response(state.queue, job, wait_s, state.wait_slots, state.stopping)


@router.post(
    "/{device_id}/recordings",
    summary="Start or stop recording a live device stream into a video job",
    status_code=201,
    responses={
        200: {"model": JobView, "description": "stopped; the job finished within Prefer: wait"},
        201: {"description": "recording started (the recording)"},
        202: {
            "model": JobAccepted,
            "description": "stopped; the video job is queued (or, when no worker has "
            f"queued it within {STOP_WAIT_S:g} s, the recording, still stopping)",
        },
        **RECORDING_ERRORS,
    },
    openapi_extra={
        "requestBody": {
            "required": False,
            "content": {
                "application/json": {"schema": RecordingFields.model_json_schema()},
                "application/x-www-form-urlencoded": {
                    "schema": RecordingFields.model_json_schema()
                },
            },
        }
    },
)
async def post_recording(
    device_id: str,
    request: Request,
    state: StateDep,
    _: SubmitKey,
    prefer: Annotated[
        list[str] | None,
        Header(description="stop: `wait=N` answers 200 with the finished job"),
    ] = None,
) -> Response:
    """``action=start`` (with video options) or ``action=stop``."""
    device = await run_in_threadpool(known_device, state, device_id)
    fields = await read_fields(request)
    if fields.action == "start":
        return await run_in_threadpool(start, state, device, fields)
    _refuse_start_fields(fields)
    wait_s = prefer_wait_s(prefer, state.settings.max_prefer_wait_s)
    return await run_in_threadpool(stop, state, device, wait_s)


@router.get(
    "/{device_id}/recordings",
    summary="The device's current (or last) recording: state, frames so far, video job",
    responses={**DEVICE_ERRORS, 404: error_response("no such device, or it never recorded")},
)
def get_recording(device_id: str, state: StateDep, _: ReadKey) -> dict[str, Any]:
    device = known_device(state, device_id)
    recording = load_recording(state.client, device)
    if recording is None:
        raise ApiError(404, "not_found", f"device {device!r} has not recorded; POST action=start")
    return recording.view()
