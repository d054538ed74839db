"""``/v1/jobs/{id}``: a job's state, its results (data files or previews), and cancelling it."""

from __future__ import annotations

import io
from typing import Annotated, Literal

import numpy as np
from fastapi import APIRouter, Query, Request, Response
from fastapi.responses import JSONResponse
from numpy.typing import NDArray
from starlette.concurrency import run_in_threadpool

from models.errors import InvalidInputError
from models.formation import encode
from models.frames import encode_frame, frame_format
from models.hdr_io import read_hdr
from models.winding_files import decode_winding, encode_winding_file
from service.api.deps import Exposure, ReadKey, StateDep, SubmitKey, refuse_unused_exposure
from service.api.downloads import MEDIA_TYPES, download, stored_file
from service.api.errors import ApiError
from service.api.idempotency import job_by_key
from service.api.in_turn import decode_in_turn
from service.api.previews import (
    codes_png,
    log_luminance_histogram,
    scene_to_wrap_units,
    tonemap_png,
    winding_png,
)
from service.api.schemas import (
    AUTH_ERRORS,
    CANNOT_HOLD,
    DECODES_BUSY,
    WRITE_REFUSED,
    JobView,
    error_response,
    job_view,
    stored_file_responses,
    video_outputs_made,
)
from service.api.state import ServiceState
from worker.jobs import JobRecord, JobState
from worker.video_jobs import video_options

router = APIRouter(prefix="/v1/jobs", tags=["jobs"])

Part = Literal["image", "winding", "codes", "histogram"]
Format = Literal["exr", "png", "npy", "tiff", "json"]
#: Formats each part comes in; the first is the default. ``png`` is always an 8-bit preview.
PART_FORMATS: dict[str, tuple[str, ...]] = {
    "image": ("exr", "png"),
    "winding": ("npy", "png", "tiff"),
    "codes": ("png", "npy", "tiff"),
    "histogram": ("json",),
}
JOB_ERRORS = {**AUTH_ERRORS, 404: error_response("no such job (or expired)")}


def finished_record(state: ServiceState, job_id: str) -> JobRecord:
    """The job's record if it succeeded; otherwise 409 saying why there is no result, with
    code ``job_not_finished`` (queued or running: poll again) or ``job_failed`` /
    ``job_cancelled`` (there never will be one: do not poll)."""
    return succeeded(state.queue.get(job_id))


def succeeded(record: JobRecord) -> JobRecord:
    """``record`` if its job succeeded; otherwise the 409 of :func:`finished_record`."""
    job_id = record.id
    if record.state == JobState.SUCCEEDED:
        return record
    if record.state.finished:
        reason = f": {record.error.message}" if record.error else ""
        message = f"job {job_id} {record.state.value}{reason}; it has no result"
        raise ApiError(409, f"job_{record.state.value}", message)
    message = f"job {job_id} is {record.state.value}; poll its state until it succeeded"
    raise ApiError(409, "job_not_finished", message)


def wrap_units(record: JobRecord, pixels: NDArray[np.float64]) -> NDArray[np.float64]:
    """The EXR's pixels in wrap units (undo the scene-referred division by the gain)."""
    if record.options.get("scene_referred", True):
        return scene_to_wrap_units(pixels, record.params.gain)
    return pixels


def wrapped_codes(record: JobRecord, x: NDArray[np.float64]) -> NDArray[np.unsignedinteger]:
    """The frame's codes, re-encoded from the reconstruction with the formation model.

    ``x_hat`` keeps each pixel's stored fraction ``m`` whatever W the decoder chose,
    so encoding it without noise gives back the uploaded codes while the EXR's precision
    holds them: for a float32 job stored before every job kept its codes
    (:func:`worker.outputs.encode_outputs`)."""
    exact = record.params.model_copy(
        update={"read_noise": 0.0, "full_well": None, "max_wraps": None}
    )
    return encode(x, exact).codes


def result_file(state: ServiceState, record: JobRecord, part: str, fmt: str, ev: float) -> Response:
    """The bytes of ``part`` in ``fmt`` for a succeeded job, made in memory from its
    stored files (all but the EXR itself: :func:`stored_exr`)."""
    stem = f"{record.id}-{part}"
    if part == "winding":
        key = record.results["winding"]
        winding = decode_winding(state.store.read(key), frame_format(key))
        if fmt == "png":
            return download(winding_png(winding), fmt, stem)
        return download(encode_winding_file(winding, fmt), fmt, stem)
    exr = state.store.read(record.results["exr"])
    x = wrap_units(record, read_hdr(exr, name="the stored result").pixels)
    if part == "image":
        return download(tonemap_png(x, ev), fmt, stem)
    if part == "histogram":
        return JSONResponse(log_luminance_histogram(x))
    codes = (
        np.load(io.BytesIO(state.store.read(record.results["codes"])), allow_pickle=False)
        if "codes" in record.results
        else wrapped_codes(record, x)
    )
    if fmt == "png":
        return download(codes_png(codes, record.params.bits), fmt, stem)
    return download(encode_frame(codes, record.params, fmt), fmt, stem)


def stored_exr(state: ServiceState, record: JobRecord) -> Response:
    """The job's EXR streamed from disk as stored (Range requests, caching)."""
    return stored_file(
        state.store, record.results["exr"], MEDIA_TYPES["exr"], f"{record.id}-image.exr"
    )


def video_files(record: JobRecord) -> str:
    """Where the video job ``record``'s files come from, with the outputs it made (or,
    not finished, will make)."""
    if record.state == JobState.SUCCEEDED:
        outputs, verb = video_outputs_made(record), "made"
    else:
        outputs, verb = video_options(record.decoder, record.options)[1], "will make"
    return f"/v1/videos/{record.id}/result?output={outputs[0]} (it {verb} {', '.join(outputs)})"


def still_record(state: ServiceState, job_id: str) -> JobRecord:
    """The record of a succeeded single-frame job; 409 for a video job, whose files come
    from ``/v1/videos/{id}/result``: ``job_not_finished`` saying so while it is queued or
    running, ``video_job`` once it succeeded (and as :func:`finished_record` otherwise)."""
    record = state.queue.get(job_id)
    if record.kind == "video" and not record.state.finished:
        raise ApiError(
            409, "job_not_finished",
            f"job {job_id} is {record.state.value}; it is a video job: once it has "
            f"succeeded, fetch its files from {video_files(record)}",
        )  # fmt: skip
    if succeeded(record).kind == "video":
        raise ApiError(
            409, "video_job",
            f"job {job_id} is a video job: fetch its files from {video_files(record)}",
        )  # fmt: skip
    return record


@router.get(
    "",
    response_model=JobView,
    responses={
        **AUTH_ERRORS,
        400: error_response("invalid_idempotency_key: not 1-255 printable ASCII characters"),
        404: error_response(
            "no request with this Idempotency-Key from this API key is remembered (none "
            "reached the server whole, it was refused, or it came more than "
            "MCAM_IDEMPOTENCY_TTL_S ago), or its job expired"
        ),
        409: error_response(
            "idempotency_key_in_use: the request with this key is still being received, "
            "decoded or queued; ask again after Retry-After"
        ),
    },
    summary="The job a request with an Idempotency-Key made",
)
def find_job(
    state: StateDep,
    key: SubmitKey,
    idempotency_key: Annotated[
        str,
        Query(description="the Idempotency-Key header the job's POST (/v1/reconstructions, "
              "/v1/videos) was sent with by this API key"),
    ],
) -> JobView:
    """Find the job of a request whose answer never came (cut off, or given up: the
    viewer's Cancel) without sending its file again, to follow or cancel it. It takes
    the submit scope, as the POST and the cancel do: a submit-only key (a camera rig's)
    got 403 for the key it had sent, which no other API key can look up."""
    return job_view(job_by_key(state, key, idempotency_key))


@router.get(
    "/{job_id}",
    response_model=JobView,
    responses=JOB_ERRORS,
    summary="A job's state, progress, timings per stage and error",
)
def get_job(job_id: str, state: StateDep, _: ReadKey) -> JobView:
    """The job's record (times in ns since the epoch, durations in ns)."""
    return job_view(state.queue.get(job_id))


@router.get(
    "/{job_id}/result",
    summary="A finished job's result: EXR, W map, wrapped codes, previews, histogram",
    response_class=Response,
    responses={
        200: {
            "content": {**{m: {} for m in MEDIA_TYPES.values()}, "application/json": {}},
            "description": "the file (png: an 8-bit preview) or the histogram JSON",
        },
        409: error_response(
            "the job has not succeeded: job_not_finished (poll again), job_failed or "
            "job_cancelled (no result will come); video_job: a video's files come from "
            "/v1/videos/{id}/result"
        ),
        **stored_file_responses("the EXR (part=image, format=exr; the others are sent whole)"),
        **JOB_ERRORS,
        422: CANNOT_HOLD,
        503: error_response(
            f"the queue (Redis) is unreachable, or (all but the EXR) {DECODES_BUSY}"
        ),
    },
)
async def get_result(
    job_id: str,
    request: Request,
    state: StateDep,
    _: ReadKey,
    part: Annotated[
        Part, Query(description="image (x_hat), winding (W), codes, histogram")
    ] = "image",
    format: Annotated[
        Format | None, Query(description="default: exr, npy, png, json by part")
    ] = None,
    exposure: Exposure = 0.0,
) -> Response:
    """``image`` as EXR (``png``: tonemapped at ``exposure`` EV, which any other file
    refuses), ``winding`` as npy/tiff (``png``: colour-coded), ``codes`` re-encoded
    (``png``: 8-bit), ``histogram``: log10 luminance counts. All but the EXR are made
    in the API's memory, a few at a time (``MCAM_MAX_CONCURRENT_DECODES``, shared with
    uploads: 503 ``server_busy`` past ``MCAM_DECODE_WAIT_S``)."""
    allowed = PART_FORMATS[part]
    fmt = format or allowed[0]
    if fmt not in allowed:
        raise InvalidInputError(
            f"part {part!r} comes as {', '.join(allowed)}, not {fmt!r}; pick one of those"
        )
    refuse_unused_exposure(request, f"part={part}&format={fmt}", "part=image&format=png")
    record = await run_in_threadpool(still_record, state, job_id)
    if part == "image" and fmt == "exr":
        return await run_in_threadpool(stored_exr, state, record)
    return await decode_in_turn(state, result_file, state, record, part, fmt, exposure)


@router.delete(
    "/{job_id}",
    response_model=JobView,
    responses={
        409: error_response("job_finished: the job already succeeded or failed"),
        **JOB_ERRORS,
        503: WRITE_REFUSED,
    },
    summary="Cancel a queued or running job",
)
def delete_job(job_id: str, state: StateDep, _: SubmitKey) -> JobView:
    """Cancel the job (a running one stops at its next check); cancelling twice is fine."""
    record = state.queue.cancel(job_id)
    if record.state in (JobState.SUCCEEDED, JobState.FAILED):
        raise ApiError(
            409, "job_finished", f"job {job_id} already {record.state.value}; nothing to cancel"
        )
    return job_view(record)
