"""``/health/live`` (the process answers) and ``/health/ready`` (it can do useful work)."""

from __future__ import annotations

import logging
import os
import shutil
from pathlib import Path
from typing import Any

import redis
from fastapi import APIRouter
from fastapi.responses import JSONResponse
from pydantic import BaseModel

from models.decoders.model_install import broken_models
from models.decoders.registry import resolve
from models.errors import McamError
from service.api.deps import StateDep
from service.api.state import ServiceState
from service.core.config import nearest_folder, upload_room
from worker.embedded_redis import redacted_url
from worker.redis_memory import free_memory, full_problem

router = APIRouter(prefix="/health", tags=["health"])
log = logging.getLogger(__name__)
#: A worker counts as alive when its heartbeat is younger than this many heartbeat periods.
HEARTBEAT_PERIODS = 3


class Liveness(BaseModel):
    status: str


class Readiness(BaseModel):
    """``checks``: decoders loaded (the default decoder resolves and every installed
    model file is the one its card describes: :func:`decoders_problem`), queue reachable
    with room (Redis has room below its maxmemory for the largest upload:
    :func:`upload_room`), workers heartbeating, result store writable with room for a
    result (name -> ok)."""

    status: str
    checks: dict[str, bool]
    workers: int
    detail: dict[str, str]


@router.get("/live", response_model=Liveness, summary="The API process is up")
def live() -> Liveness:
    return Liveness(status="ok")


def store_problem(root: Path, min_free_bytes: int) -> str | None:
    """Why workers cannot store results under ``root`` now, or None when they can: the
    folder is not writable (a read-only mount: every job fails), or its disk has less
    than ``min_free_bytes`` free (every job waits, running, until there is room). A
    folder removed since is judged by its nearest parent, where workers create it again."""
    folder = nearest_folder(root)
    if not os.access(folder, os.W_OK):
        return (
            "the result store (MCAM_DATA_DIR's results folder) is not writable: every job "
            "would fail; mount it read-write or give the service's user write access"
        )
    free = shutil.disk_usage(folder).free
    if free < min_free_bytes:
        return (
            f"the result store's disk has {free} bytes free, less than one upload "
            f"(MCAM_MAX_UPLOAD_BYTES, {min_free_bytes}): jobs would wait, running, until "
            "there is room; free space or lower MCAM_RESULT_RETENTION_S"
        )
    return None


def no_workers_problem(memory: dict[str, Any]) -> str:
    """Why no worker heartbeat is seen, from Redis's ``INFO memory`` reply: a full Redis
    refuses the heartbeats of workers that run (one more would not beat either)."""
    free = free_memory(memory)
    if free is not None and free < 0:
        return (
            "no worker heartbeat: Redis is full and refuses the workers' heartbeats, so "
            "running workers are not seen; give Redis room (see queue), then start one "
            "with 'mcam worker' if none beats"
        )
    return "no worker heartbeat: start one with 'mcam worker'"


def decoders_problem(default_decoder: str) -> str | None:
    """Why the decoders cannot serve, or None: ``default_decoder`` does not resolve, or
    an installed model file is not its card's (:func:`broken_models`: the decoder is
    listed, and its workers' warm-up only logs it, but every job that needs it fails)."""
    try:
        resolve(default_decoder)  # listed, or parametrized (auto-40ms)
    except McamError as exc:
        return f"default decoder: {exc.message}"
    try:
        broken = broken_models()
    except McamError as exc:
        log.warning("readiness: %s", exc.message)
        return "a model card is not usable (the API's log says which, and what to do)"
    return "; ".join(broken) or None


#: What an operator does about a Redis that readiness cannot reach: the log line said
#: only redis-py's words ("Connection closed by server.", from a server that is no
#: Redis), without the URL or the setting that names it.
UNREACHABLE_ADVICE = (
    "check that MCAM_REDIS_URL names a running Redis server (not another service) that "
    "this host can reach; the embedded one (unix://.../redis/redis.sock) is restarted "
    "within a second"
)


def readiness(state: ServiceState) -> Readiness:
    """Check the decoder registry and model files, Redis (reachable, with room for the
    largest upload: :func:`upload_room`), the workers' heartbeats and the result store."""
    detail: dict[str, str] = {}
    decoders = decoders_problem(state.settings.default_decoder)
    if decoders:
        detail["decoders"] = decoders
    workers = 0
    full = None
    memory: dict[str, Any] = {}
    try:
        memory = state.client.info("memory")  # answered: Redis is reachable
        reachable = True
        workers = len(state.queue.workers(HEARTBEAT_PERIODS * state.settings.heartbeat_s))
        full = full_problem(memory, upload_room(state.settings))
    except redis.exceptions.RedisError as exc:
        reachable = False
        log.warning(
            "readiness: Redis at %s unreachable: %s; %s",
            redacted_url(state.redis_url), exc, UNREACHABLE_ADVICE,
        )
        detail["queue"] = "Redis unreachable (the API's log says why)"
    if full:
        detail["queue"] = full
    if reachable and not workers:
        detail["workers"] = no_workers_problem(memory)
    problem = store_problem(state.store.root, state.settings.max_upload_bytes)
    if problem:
        detail["store"] = problem
    checks = {
        "decoders": not decoders, "queue": reachable and not full, "workers": workers > 0,
        "store": not problem,
    }
    status = "ready" if all(checks.values()) else "not_ready"
    return Readiness(status=status, checks=checks, workers=workers, detail=detail)


@router.get(
    "/ready",
    response_model=Readiness,
    responses={503: {"model": Readiness, "description": "not ready: see checks and detail"}},
    summary="Decoders loaded with their model files intact, queue reachable with room for "
    "the largest upload, workers heartbeating, result store writable",
)
def ready(state: StateDep) -> JSONResponse:
    result = readiness(state)
    return JSONResponse(result.model_dump(), status_code=200 if result.status == "ready" else 503)
