"""``POST /v1/reconstructions``: queue a wrapped frame (202; 200 with ``Prefer: wait``)."""

from __future__ import annotations

import re
from collections.abc import Sequence
from dataclasses import replace
from typing import Annotated, Any

from fastapi import APIRouter, Header, Query, Request, Response
from numpy.typing import NDArray
from starlette.concurrency import run_in_threadpool

from models.decoders.base import check_frame_shape
from models.errors import InvalidInputError, MissingParameterError
from models.file_magic import FRAME_MAGICS, format_by_content
from models.frame_params import merge_params
from models.frames import WrappedFrame, check_pixel_count, decode_frame, decode_raw
from service.api.deps import StateDep, SubmitKey
from service.api.idempotency import IdempotencyHeader, queued_job
from service.api.schemas import (
    UPLOAD_ERRORS,
    JobAccepted,
    JobView,
    job_response,
    upload_body,
)
from service.api.state import ServiceState
from service.api.uploads import (
    ReconstructionFields,
    Upload,
    sniff_frame_format,
)
from service.core.security import ApiKey
from worker.idempotency import IdempotentSubmit
from worker.jobs import JobRecord
from worker.outputs import check_result_storable

router = APIRouter(prefix="/v1", tags=["reconstructions"])

#: ``wait=N`` or ``wait="N"`` in a Prefer header, N ending at the end of the
#: preference (``wait=1e3`` or ``wait=5s`` is no wait: it was read as 1 and 5).
_WAIT = re.compile(
    r'(?:^|[,;\s])wait\s*=\s*(?:"(\d+(?:\.\d+)?)"|(\d+(?:\.\d+)?))(?=\s*(?:$|[,;]))',
    re.IGNORECASE,
)


def prefer_wait_s(prefer: str | Sequence[str] | None, limit_s: float) -> float:
    """Seconds asked for by ``Prefer: wait=N`` (RFC 7240: delta-seconds, here also a
    decimal, bare or quoted), at most ``limit_s``; 0 if absent or not a number of
    seconds (a preference the server does not understand is ignored, RFC 7240 2).
    ``prefer``: the header's value, or each of its field lines, read as one
    comma-separated list (RFC 7240 2 allows several ``Prefer`` lines: ``Prefer:
    respond-async`` then ``Prefer: wait=5`` was answered 202 at once, the wait unread)."""
    text = prefer if isinstance(prefer, str) else ", ".join(prefer or ())
    match = _WAIT.search(text)
    return min(float(match.group(1) or match.group(2)), limit_s) if match else 0.0


def read_wrapped_frame(
    upload: Upload, fields: ReconstructionFields, max_pixels: int
) -> WrappedFrame:
    """The codes and parameters of the uploaded frame (file, or raw codes + fields)."""
    raw_size = fields.width is not None and fields.height is not None
    fmt, warning = sniff_frame_format(upload, fields.format, raw_size)
    overrides = fields.sensor_overrides()
    if fmt != "raw":
        frame = decode_frame(upload.data, fmt, overrides, max_pixels)
        if warning is not None:  # declared or named raw, a PNG, TIFF or npy by its bytes
            frame = replace(frame, warnings=(warning, *frame.warnings))
    else:
        if fields.width is None or fields.height is None or fields.bits is None:
            raise MissingParameterError(
                "a raw frame needs width, height and bits (and encoding, alpha) as parameters"
            )
        check_pixel_count(fields.width, fields.height, max_pixels)
        codes = raw_codes(
            upload.data, fields.width, fields.height, fields.channels or 1, fields.bits
        )
        frame = WrappedFrame(codes, merge_params({}, overrides))
    check_frame_shape(frame.codes, frame.params)
    return frame


def raw_codes(data: bytes, width: int, height: int, channels: int, bits: int) -> NDArray[Any]:
    """The raw codes of ``data`` (:func:`models.frames.decode_raw`); a refusal of a file
    that starts as a PNG, TIFF or npy does says so (a PNG named .bin with a size given
    was told only that its byte count is wrong for the size, to check size and bits)."""
    try:
        return decode_raw(data, width, height, channels, bits)
    except InvalidInputError as exc:
        content = format_by_content(data, FRAME_MAGICS)
        if content is None:
            raise
        raise InvalidInputError(
            f"{exc.message}; its first bytes are a {content.upper()} file's: to decode it "
            f"as one, send it without format=raw, width and height (or as format={content})"
        ) from None


def choose_decoder(fields: ReconstructionFields, default: str) -> str:
    """``decoder``, the adaptive decoder at ``quality`` or within ``latency_ms``, else the
    configured default."""
    given = [name for name in ("decoder", "quality", "latency_ms") if getattr(fields, name)]
    if len(given) > 1:
        raise InvalidInputError(
            f"give one of decoder, quality and latency_ms, not {' and '.join(given)}"
        )
    if fields.quality:
        return f"auto-{fields.quality}"
    if fields.latency_ms:
        return f"auto-{fields.latency_ms:g}ms"
    return fields.decoder or default


def submit(
    state: ServiceState,
    upload: Upload,
    fields: ReconstructionFields,
    key: ApiKey,
    once: IdempotentSubmit | None = None,
) -> JobRecord:
    """Decode the upload and queue its job for ``key`` (under the request's idempotency
    key, ``once``, if any), with what the decode noticed (the file read as another format
    than its name says, 8-bit codes sent as wider) as the job's ``warnings``."""
    settings = state.settings
    frame = read_wrapped_frame(upload, fields, settings.max_pixels)
    decoder = choose_decoder(fields, settings.default_decoder)
    options = {
        "scene_referred": fields.scene_referred,
        "half": fields.half,
        "exr_compression": fields.exr_compression,
    }
    check_result_storable(frame.codes, frame.params, options)
    return state.queue.submit(
        "reconstruction", frame.codes, frame.params, decoder, options, owner=key.id,
        warnings=frame.warnings, idempotency=once,
    )


@router.post(
    "/reconstructions",
    summary="Reconstruct an HDR image from a wrapped frame (asynchronous job)",
    status_code=202,
    response_model=JobAccepted,
    responses={
        200: {"model": JobView, "description": "finished within the Prefer: wait time"},
        202: {"model": JobAccepted, "description": "queued: poll the job's url"},
        **UPLOAD_ERRORS,
    },
    openapi_extra=upload_body(ReconstructionFields, "a wrapped frame (.png, .tiff, .npy, raw)"),
)
async def post_reconstruction(
    request: Request,
    query: Annotated[ReconstructionFields, Query()],
    state: StateDep,
    key: SubmitKey,
    prefer: Annotated[
        list[str] | None,
        Header(description="`wait=N`: answer 200 with the job if done within N s"),
    ] = None,
    idempotency_key: IdempotencyHeader = None,
) -> Response:
    """Queue a wrapped frame; the job's state is at ``GET /v1/jobs/{id}``. Only the
    decode and the submit hold a decode slot, not the ``Prefer: wait`` for the job. A
    repeat of a request with its ``Idempotency-Key`` is answered with its job
    (:mod:`service.api.idempotency`)."""
    record = await queued_job(
        request, query, ReconstructionFields, state, key, idempotency_key, submit
    )
    wait_s = prefer_wait_s(prefer, state.settings.max_prefer_wait_s)
    return await run_in_threadpool(
        job_response, state.queue, record, wait_s, state.wait_slots, state.stopping
    )
