"""``/v1/devices``: camera links (health from the daemons), control commands, the newest
reconstruction; forgetting a retired camera. Its event stream: :mod:`.device_events`."""

from __future__ import annotations

import json
import time
from typing import Annotated, Any, Literal

import redis
from fastapi import APIRouter, Body, Request, Response
from starlette.concurrency import run_in_threadpool

from device.commands import Command, command_fields
from device.health import ALL_DROP_CAUSES, ENDED_STATES
from models.hdr_io import read_hdr
from service.api.deps import Exposure, ReadKey, StateDep, SubmitKey, refuse_unused_exposure
from service.api.downloads import MEDIA_TYPES, download, stored_file
from service.api.errors import ApiError
from service.api.in_turn import decode_in_turn
from service.api.previews import scene_to_wrap_units, tonemap_png
from service.api.schemas import (
    AUTH_ERRORS,
    DECODES_BUSY,
    SMALL_BODY_ERRORS,
    WRITE_REFUSED,
    error_response,
    stored_file_responses,
)
from service.api.state import ServiceState
from worker.control_queue import queue_command
from worker.device_registry import DeviceNotFoundError, forget_device
from worker.redis_keys import (
    DEVICES_SET,
    health_key,
    latest_key,
    validate_device_id,
)

router = APIRouter(prefix="/v1/devices", tags=["devices"])
DEVICE_ERRORS = {**AUTH_ERRORS, 404: error_response("no such device")}
#: ``DELETE /v1/devices/{id}``'s 409.
_FORGET_BUSY = error_response(
    "device_busy: its daemon reports, it records, or frames wait to be decoded"
)
#: Responses of ``POST /v1/devices/{id}/control``, whose body is a JSON command.
CONTROL_ERRORS = {
    **DEVICE_ERRORS,
    **SMALL_BODY_ERRORS,
    400: error_response(
        "bad_request: the JSON body could not be parsed (nested too deeply, or an integer "
        "of more than 4300 digits)"
    ),
    503: error_response(
        "control_backlog_full: commands already wait unread (nothing was queued); or the "
        "queue (Redis) is unreachable or full (queue_unavailable, store_full)"
    ),
}
#: A device whose daemon has not written its health for this long (s; it writes every
#: 0.25 s) is shown as ``silent``: the daemon was killed, or lost Redis (one that ended,
#: :data:`ENDED_STATES`, said so). Its last reported state stays in ``last_state``.
DAEMON_SILENT_S = 10.0


def as_text(value: bytes | str) -> str:
    """A Redis reply as text."""
    return value.decode() if isinstance(value, bytes) else value


def _number(value: str) -> Any:
    try:
        return int(value)
    except ValueError:
        try:
            return float(value)
        except ValueError:
            return value


#: Health fields that stay text (the others are numbers).
_TEXT_FIELDS = ("device", "port", "state", "crash", "port_error")


def device_view(client: redis.Redis, device: str) -> dict[str, Any]:
    """A device's health hash as JSON: counters as numbers, drops grouped by cause; a
    device whose daemon ended (stopped, or crashed: ``crash`` says on what) or went
    silent at 0 fps."""
    fields = {as_text(k): as_text(v) for k, v in client.hgetall(health_key(device)).items()}
    view: dict[str, Any] = {"id": device, "dropped": {}}
    for name, value in fields.items():
        if name.startswith("dropped_") and name[len("dropped_"):] in ALL_DROP_CAUSES:
            view["dropped"][name[len("dropped_"):]] = int(value)
        elif name == "settings":
            view["settings"] = json.loads(value or "{}")
        else:
            view[name] = value if name in _TEXT_FIELDS else _number(value)
    latest = client.get(latest_key(device))
    view["latest_result"] = as_text(latest) if latest else None
    updated = view.get("updated_ns")
    if isinstance(updated, int):
        view["age_s"] = round((time.time_ns() - updated) / 1e9, 3)
        if view["age_s"] > DAEMON_SILENT_S and view.get("state") not in ENDED_STATES:
            view["last_state"], view["state"], view["fps"] = view.get("state"), "silent", 0.0
    if view.get("state") in ENDED_STATES:  # its last write measured the frames before the end
        view["fps"] = 0.0
    return view


def known_device(state: ServiceState, device: str) -> str:
    """``device`` if valid and registered by a daemon; 404 otherwise."""
    validate_device_id(device)
    if not state.client.sismember(DEVICES_SET, device):
        raise DeviceNotFoundError(device)
    return device


@router.get("", responses=AUTH_ERRORS, summary="List devices with their health")
def list_devices(state: StateDep, _key: ReadKey) -> dict[str, list[dict[str, Any]]]:
    devices = sorted(as_text(d) for d in state.client.smembers(DEVICES_SET))
    return {"devices": [device_view(state.client, d) for d in devices]}


@router.get("/{device_id}", responses=DEVICE_ERRORS, summary="One device's health and settings")
def get_device(device_id: str, state: StateDep, _key: ReadKey) -> dict[str, Any]:
    return device_view(state.client, known_device(state, device_id))


@router.delete("/{device_id}", responses={**DEVICE_ERRORS, 409: _FORGET_BUSY,
                                          503: WRITE_REFUSED},
               summary="Forget a device whose daemon has stopped (its keys, not its results)")
def forget(device_id: str, state: StateDep, _key: SubmitKey,
           discard_frames: bool = False) -> dict[str, Any]:
    """409 ``device_busy`` while its daemon reports, it records, or frames wait to be
    decoded (``discard_frames=true`` drops those); 404 when another request forgot it
    first. Stored reconstructions stay until their retention ends; a daemon that comes
    back registers the device again."""
    device = known_device(state, device_id)
    dropped = forget_device(state.client, device, silent_after_s=DAEMON_SILENT_S,
                            discard_frames=discard_frames)
    return {"device": device, "forgotten": True, "frames_discarded": dropped}


@router.post("/{device_id}/control", status_code=202,
             responses=CONTROL_ERRORS,
             summary="Send a control command to the camera (via its daemon)")
def control(device_id: str, command: Annotated[Command, Body()], state: StateDep,
            _key: SubmitKey) -> dict[str, Any]:
    """503 ``control_backlog_full`` (nothing queued) while the daemon has not read the
    commands already waiting for it."""
    device = known_device(state, device_id)
    entry = queue_command(state.client, device, command_fields(command))
    return {"device": device, "entry": entry, "command": command.model_dump()}


#: The newest frame's 503 (all but the EXR: its preview is made in the API's memory).
_PREVIEW_BUSY = error_response(f"Redis is unreachable, or (format=png) {DECODES_BUSY}")
#: The newest frame's 404.
_NO_FRAME = error_response("no such device, or it has no reconstructed frame yet")


def latest_result(state: ServiceState, device_id: str) -> tuple[str, str]:
    """The device's name and the result-store key of its newest reconstruction (404 if
    the device is unknown or has none yet)."""
    device = known_device(state, device_id)
    key = state.client.get(latest_key(device))
    if not key:
        raise ApiError(404, "not_found", f"device {device!r} has no reconstructed frame yet")
    return device, as_text(key)


def frame_preview(state: ServiceState, key: str, exposure: float, stem: str) -> Response:
    """The stored frame ``key`` tonemapped at ``exposure`` EV, as a PNG."""
    image = read_hdr(state.store.read(key), name="the stored result")
    gain = image.attributes.get("gain")  # device frames are stored scene-referred
    x = scene_to_wrap_units(image.pixels, float(gain) if gain else None)
    return download(tonemap_png(x, exposure), "png", stem)


@router.get("/{device_id}/frames/latest",
            responses={**stored_file_responses("the EXR (format=exr; the PNG is sent whole)"),
                       **DEVICE_ERRORS, 404: _NO_FRAME, 503: _PREVIEW_BUSY},
            summary="The newest reconstructed frame: EXR, or a tonemapped PNG preview")
async def latest_frame(device_id: str, request: Request, state: StateDep, _key: ReadKey,
                       format: Literal["exr", "png"] = "exr",
                       exposure: Exposure = 0.0) -> Response:
    """The EXR is streamed as stored; the PNG (tonemapped at ``exposure`` EV, which the
    EXR refuses) is made in the API's memory, a few at a time
    (``MCAM_MAX_CONCURRENT_DECODES``, shared with uploads and job previews)."""
    refuse_unused_exposure(request, f"format={format}", "format=png")
    device, key = await run_in_threadpool(latest_result, state, device_id)
    stem = f"{device}-latest"
    if format == "exr":
        return await run_in_threadpool(
            stored_file, state.store, key, MEDIA_TYPES["exr"], f"{stem}.exr", immutable=False
        )
    return await decode_in_turn(state, frame_preview, state, key, exposure, stem)
