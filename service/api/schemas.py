"""Response bodies and the OpenAPI descriptions shared by the routers."""

from __future__ import annotations

import logging
import threading
from typing import Any

import redis
from fastapi.responses import JSONResponse
from pydantic import BaseModel, Field

from service.api.state import Slots
from worker.jobs import JobRecord, JobState
from worker.queue import JobQueue
from worker.redis_memory import is_transient, redis_trouble
from worker.video_pipeline import OUTPUTS as VIDEO_OUTPUTS

log = logging.getLogger(__name__)


class ErrorBody(BaseModel):
    """Every error: a stable machine-readable ``code`` and a message saying what to do."""

    code: str
    message: str
    parameters: list[str] | None = Field(
        None,
        description="the parameters (form field names) the message asks to give, where it "
        "asks for some: a frame that does not store them, or stores them unreadable or "
        "out of range",
    )


class JobAccepted(BaseModel):
    """A queued job: poll ``url`` for its state. ``warnings``: what reading the upload
    noticed that the sender should know (also in the job's state)."""

    id: str
    url: str
    state: JobState
    warnings: list[str] = Field(
        default_factory=list,
        description="e.g. a file named as another format than its content, which was read "
        "as its content",
    )


def accepted_response(record: JobRecord) -> JSONResponse:
    """202 with the queued job's id, URL (also in ``Location``) and warnings."""
    url = f"/v1/jobs/{record.id}"
    accepted = JobAccepted(id=record.id, url=url, state=record.state, warnings=record.warnings)
    return JSONResponse(
        accepted.model_dump(mode="json"), status_code=202, headers={"Location": url}
    )


def job_response(
    queue: JobQueue, record: JobRecord, wait_s: float, slots: Slots, stop: threading.Event
) -> JSONResponse:
    """200 with the job if it finishes within ``wait_s`` (``Prefer: wait``), else 202.
    A wait holds a server thread, so only as many requests as ``slots`` allows wait at
    once; the others get their 202 at once (42 waiting uploads from one key made every
    other request wait 22 s for a thread). A wait ends with the 202 once ``stop`` is set
    (the server is stopping): it held the stop for the whole grace period, and its client
    then got a 500 for a job that was stored."""
    if wait_s > 0 and slots.take():
        try:
            record = queue.wait(record.id, wait_s, stop)
        except redis.exceptions.RedisError as exc:
            if not is_transient(exc):
                raise
            # The job is accepted and stored: an answer of 503 would have the client
            # submit it again, so it gets its 202 and polls once Redis is back.
            log.warning("job %s: the wait for it ended early: %s", record.id, redis_trouble(exc))
        finally:
            slots.release()
        if record.state.finished:
            return JSONResponse(
                job_view(record).model_dump(mode="json"),
                headers={"Location": f"/v1/jobs/{record.id}",
                         "Preference-Applied": f"wait={wait_s:g}"},
            )
    return accepted_response(record)


class JobView(JobRecord):
    """A job's record plus the URLs of its resources (``self``, ``result``)."""

    links: dict[str, str]


def video_outputs_made(record: JobRecord) -> list[str]:
    """The outputs (:data:`worker.video_pipeline.OUTPUTS`, in that order) whose files the
    video job ``record`` made."""
    return [name for name in VIDEO_OUTPUTS if name in record.results]


def job_view(record: JobRecord) -> JobView:
    """The API view of a job record. A succeeded video job links each file it made
    (``result_hdr10`` ...) and, as ``result``, the first of hdr10, sdr, exr_zip: its
    files come from ``/v1/videos/{id}/result`` (``/v1/jobs/{id}/result`` answers 409)."""
    base = f"/v1/jobs/{record.id}"
    links = {"self": base}
    if record.state == JobState.SUCCEEDED and record.kind == "video":
        files = {
            f"result_{name}": f"/v1/videos/{record.id}/result?output={name}"
            for name in video_outputs_made(record)
        }
        links |= {"result": next(iter(files.values()))} if files else {}
        links |= files
    elif record.state == JobState.SUCCEEDED:
        links["result"] = f"{base}/result"
    return JobView(**record.model_dump(), links=links)


#: Why a route that decodes or makes previews in the API's memory may answer 503
#: server_busy (:func:`service.api.in_turn.decode_in_turn`).
DECODES_BUSY = (
    "the API is decoding uploads or making previews MCAM_MAX_CONCURRENT_DECODES at a time "
    "and none finished within MCAM_DECODE_WAIT_S (server_busy, see Retry-After)"
)


def error_response(description: str) -> dict[str, Any]:
    return {"model": ErrorBody, "description": description}


AUTH_ERRORS: dict[int | str, dict[str, Any]] = {
    401: error_response("missing or unknown API key"),
    403: error_response("the API key lacks the scope"),
    422: error_response("invalid parameters"),
    429: error_response("rate limit exceeded (see Retry-After)"),
    503: error_response("queue_unavailable: the queue (Redis) is unreachable (see Retry-After)"),
}
#: The 503 of a route that writes to Redis: a full Redis refuses the write (reads go on).
WRITE_REFUSED = error_response(
    "the queue (Redis) is unreachable (queue_unavailable) or at its maxmemory (store_full: "
    "nothing of the request was stored); see Retry-After"
)
#: Responses of a route that reads a request body (``service.api.body_timeout``).
BODY_ERRORS: dict[int | str, dict[str, Any]] = {
    408: error_response(
        "the request body paused longer than MCAM_HTTP_BODY_TIMEOUT_S, or took longer "
        "than MCAM_HTTP_BODY_DEADLINE_S in all"
    ),
}
#: Responses of a route that reads a JSON or URL-encoded body (``service.api.body_limit``).
SMALL_BODY_ERRORS: dict[int | str, dict[str, Any]] = {
    **BODY_ERRORS,
    413: error_response("body_too_large: the JSON or form body is over MCAM_MAX_JSON_BYTES"),
}
#: The 503 of a route that queues a job: Redis unreachable or full, the queue full.
QUEUE_REFUSALS = (
    "the queue (Redis) is unreachable (queue_unavailable) or full: queue_full (MCAM_JOBS_MAXLEN "
    "jobs, or MCAM_JOBS_MAX_BYTES of codes, queued) or store_full (Redis at its maxmemory)"
)


def stored_file_responses(which: str) -> dict[int | str, dict[str, Any]]:
    """The answers besides 200 of a route sending ``which`` (a file as stored:
    :func:`service.api.downloads.stored_file`) to Range and conditional requests (RFC 9110
    13-15); the OpenAPI document named none of them, so a client generated from it knew
    of no 206 or 304."""
    return {
        206: {"description": f"{which}: the byte ranges the Range header asked for "
              "(Content-Range; several ranges: multipart/byteranges)"},
        304: {"description": f"{which}: not modified, no body: If-None-Match names its "
              "ETag, or If-Modified-Since is no earlier than its Last-Modified"},
        400: error_response(
            f"{which}: bad_range: the Range header is malformed; ask for bytes=FIRST-LAST, "
            "bytes=FIRST- or bytes=-LENGTH, or send none for the whole file"
        ),
        412: error_response(
            f"{which}: precondition_failed: If-Match or If-Unmodified-Since names another "
            "version of the file (its ETag is in the answer); fetch it again whole, without them"
        ),
        416: error_response(
            f"{which}: range_not_satisfiable: no range of the Range header lies in the file "
            "(its size is in Content-Range); ask for bytes within it"
        ),
    }


#: The 422 of a route that writes a result in the format asked for.
CANNOT_HOLD = error_response(
    "invalid parameters, or format_cannot_hold_result: the output format asked for cannot "
    "hold this result (a colour frame or W map as PNG, W over 65535 as a 16-bit PNG or "
    "TIFF; the message names the formats that can)"
)
#: Responses of ``POST /v1/simulate``, which reads an upload and queues no job.
SIMULATE_ERRORS: dict[int | str, dict[str, Any]] = {
    **AUTH_ERRORS,
    **BODY_ERRORS,
    400: error_response("malformed request body"),
    413: error_response("upload or image too large"),
    415: error_response(
        "unsupported_format: the upload's file format or content type is not one read here"
    ),
    429: error_response("rate limit exceeded (rate_limited, see Retry-After)"),
    503: error_response(
        f"the queue (Redis) is unreachable (queue_unavailable), or {DECODES_BUSY}"
    ),
}
#: Responses of a route that reads an upload and queues its job.
UPLOAD_ERRORS: dict[int | str, dict[str, Any]] = {
    **SIMULATE_ERRORS,
    400: error_response(
        "malformed request body, or invalid_idempotency_key: the Idempotency-Key is not "
        "1-255 printable ASCII characters, or came on several lines naming different keys"
    ),
    409: error_response(
        "idempotency_key_in_use: a request with this Idempotency-Key is still being "
        "received, decoded or queued; ask again after Retry-After"
    ),
    422: error_response(
        "invalid parameters, or idempotency_key_reused: this Idempotency-Key came before "
        "with other parameters, another file or file name, or on the other route"
    ),
    429: error_response(
        "rate limit exceeded (rate_limited, see Retry-After), or the key's jobs in the "
        "queue reach MCAM_MAX_QUEUED_JOBS_PER_KEY or MCAM_MAX_QUEUED_BYTES_PER_KEY "
        "(too_many_jobs)"
    ),
    503: error_response(f"{QUEUE_REFUSALS}, or {DECODES_BUSY}"),
}


def _plain(schema: dict[str, Any]) -> dict[str, Any]:
    """A property schema without its ``null`` alternative (form fields are never null)."""
    options = [s for s in schema.get("anyOf", []) if s.get("type") != "null"]
    if len(options) != 1:
        return schema
    rest = {k: v for k, v in schema.items() if k != "anyOf"}
    return {**options[0], **rest}


def upload_body(fields: type[BaseModel], what: str) -> dict[str, Any]:
    """OpenAPI ``requestBody``: multipart (``file`` + form ``fields``) or a raw body."""
    schema = fields.model_json_schema()
    properties = {
        "file": {"type": "string", "format": "binary", "description": what},
        **{name: _plain(prop) for name, prop in schema["properties"].items()},
    }
    return {
        "requestBody": {
            "required": True,
            "content": {
                "multipart/form-data": {
                    "schema": {"type": "object", "properties": properties, "required": ["file"]}
                },
                "application/octet-stream": {
                    "schema": {"type": "string", "format": "binary", "description": what}
                },
            },
        }
    }
