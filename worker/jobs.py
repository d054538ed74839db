"""The record of one job as stored in Redis (``job:<id>``) and shown by the API.

Times are in ns since the epoch (``time.time_ns()``); durations in ns. A job's times are
taken on the clocks of the machines that handle it (the API's: created, cancelled; a
worker's: started, finished), which may disagree: :func:`time_after` keeps them in order.
"""

from __future__ import annotations

import re
import time
from enum import StrEnum
from typing import Any, Literal

from pydantic import BaseModel, Field

from models.errors import McamError, echo
from models.formation import SensorParams

_JOB_ID = re.compile(r"^[0-9a-f]{32}$")


class JobState(StrEnum):
    """Life cycle: queued -> running -> succeeded | failed | cancelled."""

    QUEUED = "queued"
    RUNNING = "running"
    SUCCEEDED = "succeeded"
    FAILED = "failed"
    CANCELLED = "cancelled"

    @property
    def finished(self) -> bool:
        return self in (JobState.SUCCEEDED, JobState.FAILED, JobState.CANCELLED)


class JobError(BaseModel):
    """Why a job failed: a stable code and a human message."""

    code: str
    message: str


class JobRecord(BaseModel):
    """Everything known about a job. ``results`` maps an output name (``exr``,
    ``winding``, ``hdr10``, ``sdr``, ``exr_zip``) to its result-store key."""

    id: str
    kind: Literal["reconstruction", "video"] = "reconstruction"
    state: JobState = JobState.QUEUED
    decoder: str
    params: SensorParams
    options: dict[str, Any] = Field(default_factory=dict)
    progress: float = 0.0
    frames_done: int = 0
    frames_total: int = 1
    created_ns: int
    started_ns: int | None = Field(
        None,
        description="when a worker started the job (ns since the epoch; kept through its "
        "retries and a takeover from a worker that died); null while it is queued, also "
        "after a stopping worker handed it back to the queue",
    )
    finished_ns: int | None = None
    timings_ns: dict[str, int] = Field(default_factory=dict)
    error: JobError | None = None
    results: dict[str, str] = Field(default_factory=dict)
    info: dict[str, Any] = Field(default_factory=dict)
    attempts: int = 0
    #: What reading the uploaded file noticed that its sender should know (a file named
    #: as another format than its content: read as its content; codes all below 256
    #: although bits says more), set when it is queued.
    warnings: list[str] = Field(default_factory=list)


class JobNotFoundError(McamError):
    """No job with that id (or the id is malformed)."""

    code = "not_found"
    http_status = 404


def validate_job_id(job_id: str) -> str:
    """Job ids are 32 lowercase hex digits; anything else is not found (never a path),
    with an error that says lower case (an id in capitals was told "job ids are 32
    hexadecimal digits", which it is)."""
    if not _JOB_ID.fullmatch(job_id):
        raise JobNotFoundError(
            f"no job {echo(job_id)}: job ids are 32 hexadecimal digits in lower case "
            "(0-9, a-f), as the job's url gives them"
        )
    return job_id


def time_after(*earlier_ns: int | None) -> int:
    """Now (ns since the epoch), or the latest of ``earlier_ns`` (times this job already
    has, None: not set) where that is later: the clock of the machine that takes this
    time may be behind the one that took those (an API and a worker on two machines),
    and a job then showed a finish before its start, or a negative queue wait."""
    return max(time.time_ns(), *(t for t in earlier_ns if t is not None))
