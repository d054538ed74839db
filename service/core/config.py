"""Deployment settings, read from ``MCAM_*`` environment variables and an optional ``.env``.

The same settings configure the API, the workers and the device daemons; the
CLI reads them and passes plain values into ``worker/`` and ``device/``.
"""

from __future__ import annotations

import contextlib
import io
import logging
import os
import shutil
from collections.abc import Iterable, Mapping
from difflib import get_close_matches
from functools import cache
from pathlib import Path
from typing import Literal, get_args

from dotenv.parser import Binding, parse_stream
from pydantic import Field, ValidationInfo, field_validator, model_validator
from pydantic_settings import BaseSettings, SettingsConfigDict

from device.datasets import DEFAULT_MAX_BYTES, DEFAULT_MAX_PAIRS
from models.decoders.measured import report_problem
from models.decoders.registry import resolve
from models.errors import InvalidInputError, McamError
from models.hdr_io import EXR_COMPRESSIONS
from worker.config_checks import heartbeat_problem
from worker.embedded_redis import url_problem
from worker.outputs import STREAM_EXR_COMPRESSION
from worker.recordings import MAX_RECORDING_SAMPLES
from worker.redis_memory import DEFAULT_MAXMEMORY, submit_room

log = logging.getLogger(__name__)

#: Most onnxruntime intra-op threads a worker's session may have (``--threads``).
MAX_WORKER_THREADS = 256
#: Most jobs one worker decodes at once (``--concurrency``): each job thread keeps a
#: decoding process of its own (about 165 MB before it decodes), one per core of the
#: largest machines.
MAX_WORKER_CONCURRENCY = 256
#: Most processes decoding one worker's device streams (``--stream-processes``), each
#: holding its own networks: one per core of the largest machines.
MAX_STREAM_POOL_PROCESSES = 256
#: Most workers ``mcam serve --workers`` runs, each a process of about 300 MB with its
#: decoding processes: one per core of the largest machines.
MAX_SERVE_WORKERS = 256
#: Most bytes of an unfinished request head (``MCAM_HTTP_MAX_HEADER_BYTES``): 1 MiB.
MAX_HTTP_HEADER_BYTES = 2**20
#: Most bytes of a JSON or URL-encoded body (``MCAM_MAX_JSON_BYTES``): 1 MiB.
MAX_JSON_BYTES = 2**20
#: Longest ``MCAM_RESULT_RETENTION_S`` (s): 100 years.
MAX_RESULT_RETENTION_S = 100 * 365.25 * 24 * 3600
#: Longest ``MCAM_DEVICE_LEASE_MS`` and ``MCAM_CLAIM_IDLE_MS`` (ms): a day.
MAX_TAKEOVER_MS = 24 * 3600 * 1000
#: Most deliveries of an entry (``MCAM_MAX_DELIVERIES``).
MAX_DELIVERIES = 10
#: Shortest ``MCAM_HTTP_*_TIMEOUT_S`` and ``MCAM_HTTP_BODY_DEADLINE_S`` (s): one lost
#: packet alone stalls a connection for TCP's initial retransmission timeout, 1 s.
MIN_HTTP_TIMEOUT_S = 1.0
#: Shortest ``MCAM_HEARTBEAT_S`` (s).
MIN_HEARTBEAT_S = 0.1
#: Bytes an embedded Redis holds before any job (0.93 MB measured on an empty one),
#: with room to spare.
EMPTY_REDIS_BYTES = 2 * 1024**2
#: What every setting's variable begins with.
PREFIX = "MCAM_"
#: Encoding of ``.env``.
ENV_FILE_ENCODING = "utf-8"
#: Most frames ``MCAM_FRAMES_MAXLEN`` keeps per device stream: 2^20.
MAX_FRAMES_MAXLEN = 2**20


class Settings(BaseSettings):
    """All ``MCAM_*`` settings. Sizes in bytes or pixels, times in seconds unless named ``_ms``."""

    #: An empty variable (``MCAM_PORT=``, or compose's ``${VAR}`` of an unset one) is
    #: unset: it took ``MCAM_DATA_DIR=`` as the working folder and refused ``MCAM_PORT=``.
    #: A time that is no finite number is refused as such: ``MCAM_DECODE_WAIT_S=nan`` was
    #: told "Input should be less than or equal to 300", which nan is not far from.
    model_config = SettingsConfigDict(
        env_prefix=PREFIX, env_file=".env", env_file_encoding=ENV_FILE_ENCODING,
        extra="ignore", env_ignore_empty=True, allow_inf_nan=False,
    )

    data_dir: Path = Field(Path("data"), description="results, embedded Redis, API key file")
    redis_url: str | None = Field(
        None, description="external Redis (redis://, rediss://, unix://); unset: embedded redis"
    )
    api_keys: str | None = Field(
        None,
        description="comma-separated 'KEY' (read+submit) or 'KEY:read' / 'KEY:submit'; "
        "unset: one key is generated on first start and stored in the data dir",
    )
    host: str = "127.0.0.1"
    port: int = Field(8000, ge=1, le=65535)
    http_keep_alive_s: int = Field(
        5, ge=1, le=3600,
        description="an idle keep-alive connection is closed after this many seconds (at "
        "most an hour: each holds one of MCAM_HTTP_MAX_CONNECTIONS, and at 1e400 each "
        "response logged an OverflowError traceback)",
    )  # fmt: skip
    http_shutdown_grace_s: float = Field(
        5.0, gt=0, le=300,
        description="on SIGTERM, seconds open requests (an event stream) may run on before "
        "they are closed and the server stops",
    )  # fmt: skip
    http_max_connections: int = Field(
        256, ge=2,
        description="open HTTP connections and requests at once; a request beyond them: 503",
    )  # fmt: skip
    http_max_header_bytes: int = Field(
        16 * 1024, ge=1024, le=MAX_HTTP_HEADER_BYTES,
        description="uvicorn/h11 h11_max_incomplete_event_size: bytes buffered while the "
        "request line and headers are incomplete, then 400 (not a bound on the headers: "
        "ones that arrive in one read may be longer); at most 1 MiB, past any client's "
        "need: at 1e19 one client's unfinished head grew the API by 350 MB in 2.3 s",
    )  # fmt: skip
    http_header_timeout_s: float = Field(
        10.0, ge=MIN_HTTP_TIMEOUT_S, le=3600,
        description="longest a request's line and headers may take (from the connection's "
        "start or the request's first byte) before 408 and the connection closed; at "
        "least 1 s (TCP's first retransmission: at 1e-9 the local host's curl got no "
        "answer to 4 requests in 10)",
    )  # fmt: skip
    http_body_timeout_s: float = Field(
        30.0, ge=MIN_HTTP_TIMEOUT_S, le=3600,
        description="longest pause in a request body before 408 (a slow upload holds a "
        "task); at least 1 s: at 1e-9 every 4 MB upload got 408, its client blamed",
    )  # fmt: skip
    http_body_deadline_s: float = Field(
        300.0, ge=MIN_HTTP_TIMEOUT_S, le=86_400,
        description="longest a request body may take in all, from the app's first read of "
        "it, before 408: a body trickling in never pauses for MCAM_HTTP_BODY_TIMEOUT_S "
        "(the 64 MiB upload limit in 300 s needs 1.8 Mbit/s); at least 1 s: at 1e-9 "
        "every upload got 408",
    )  # fmt: skip
    max_upload_bytes: int = Field(64 * 1024 * 1024, gt=0)
    max_json_bytes: int = Field(
        64 * 1024, gt=0, le=MAX_JSON_BYTES,
        description="a JSON or URL-encoded body (commands, form fields: a few hundred bytes), "
        "at most 1 MiB: one is parsed before its API key is checked, and at 1e19 a 100 MB "
        "body from no key at all took the API 300 MB before its 401",
    )  # fmt: skip
    max_pixels: int = Field(4096 * 4096, gt=0, description="per frame (all frames of a video)")
    max_video_frames: int = Field(600, gt=0)
    max_video_samples: int = Field(
        MAX_RECORDING_SAMPLES,
        gt=0,
        le=2 * MAX_RECORDING_SAMPLES,
        description="code values of a whole video (frames x pixels x channels); a job "
        "stores them as one Redis value (2 bytes each, Redis takes at most 512 MB) and a "
        "worker holds about 20 bytes each while decoding",
    )
    rate_limit_per_minute: int = Field(600, gt=0, description="requests per API key in any 60 s")
    metrics_public: bool = Field(
        False,
        description="serve /metrics without an API key (a scraper on a private network); "
        "by default it needs a key with the read scope, as device ids and load are in it",
    )
    max_waiting_requests: int = Field(
        16, ge=0, le=32,
        description="requests held open at once by 'Prefer: wait' (the API has 40 threads)",
    )  # fmt: skip
    max_concurrent_decodes: int = Field(
        2, ge=1, le=40,
        description="uploads the API decodes or simulates (POST /v1/simulate, "
        "/v1/reconstructions, /v1/videos) and results it previews (GET /v1/jobs/{id}/result "
        "but the EXR, a device's PNG frame) at once, all in its own memory: a 4096 x 4096 "
        "simulate peaks at 3.6 GB; one more waits up to MCAM_DECODE_WAIT_S for its turn, "
        "then 503",
    )  # fmt: skip
    decode_wait_s: float = Field(
        10.0, ge=0, le=300,
        description="longest an upload or preview waits for one of MCAM_MAX_CONCURRENT_DECODES "
        "before 503 server_busy with Retry-After (it holds no server thread meanwhile)",
    )  # fmt: skip
    max_event_streams: int = Field(
        64, ge=1, le=10_000,
        description="server-sent event streams open at once (each holds a Redis connection)",
    )  # fmt: skip
    max_prefer_wait_s: float = Field(
        60.0, ge=0, le=3600,
        description="longest 'Prefer: wait=N' a request may block for its job (at most an "
        "hour: a wait holds a server thread and one of MCAM_MAX_WAITING_REQUESTS even once "
        "its client has gone, and at inf one that gave up held them for good)",
    )  # fmt: skip
    default_decoder: str = Field(
        "auto", description="decoder when a request names neither decoder nor quality"
    )
    accuracy_report: Path | None = Field(
        None,
        description="the val-256 benchmark's report (python -m bench.accuracy) that gives "
        "GET /v1/decoders the figures of decoders without a model card (classical, +puma, "
        "auto); unset: bench/results/accuracy.json of the repository checkout",
    )
    worker_concurrency: int = Field(
        1, ge=1, le=MAX_WORKER_CONCURRENCY,
        description="jobs decoded at once per worker, each in a process of about 165 MB "
        "(at most 256: 1e19 grew the worker until it ran out of memory)",
    )  # fmt: skip
    worker_threads: int = Field(
        2, ge=1, le=MAX_WORKER_THREADS,
        description="onnxruntime intra-op threads per session (at most 256: 100000 had a "
        "job's decoding process grow by 4.5 GB a minute and never finish a 64 x 64 frame)",
    )  # fmt: skip
    ort_spin: bool = Field(
        False,
        description="idle onnxruntime threads spin: faster on cores nothing else uses, "
        "much slower on shared ones",
    )
    jobs_maxlen: int = Field(10_000, gt=0, description="jobs stream bound; submits beyond it: 503")
    jobs_max_bytes: int = Field(
        2 * 1024**3, gt=0,
        description="bytes of codes all jobs in the queue may hold in Redis; submits beyond: 503",
    )  # fmt: skip
    redis_maxmemory: int = Field(
        DEFAULT_MAXMEMORY, gt=0,
        description="bytes the embedded Redis may use (maxmemory, noeviction): beyond them it "
        "refuses writes (submits: 503 store_full) and drops nothing; an external Redis "
        "keeps its own setting",
    )  # fmt: skip
    max_queued_jobs_per_key: int = Field(
        64, gt=0, description="jobs one API key may have in the queue; more: 429"
    )
    max_queued_bytes_per_key: int = Field(
        512 * 1024**2, gt=0,
        description="bytes of codes one API key's jobs may hold in the queue; more: 429",
    )  # fmt: skip
    frames_maxlen: int = Field(
        256, gt=0, le=MAX_FRAMES_MAXLEN,
        description="per-device frame stream bound (drop oldest); at most 2^20 (64 GiB of "
        "256 x 256 codes): Redis refuses a MAXLEN of 2^63, and 1e19 dropped every frame",
    )  # fmt: skip
    claim_idle_ms: int = Field(
        30_000, gt=0, le=MAX_TAKEOVER_MS,
        description="reclaim entries pending this long (at most a day: Redis refuses an "
        "idle time of 2^63 ms or more, and 1e19 left every job queued, never read)",
    )  # fmt: skip
    max_deliveries: int = Field(
        3, ge=1, le=MAX_DELIVERIES,
        description="then the entry goes to the dead letters; at most 10 (retries wait 0.05 s "
        "doubled per delivery: 1000 stalled a failing job for days, deaf to SIGTERM)",
    )  # fmt: skip
    device_lease_ms: int = Field(
        5_000, gt=0, le=MAX_TAKEOVER_MS,
        description="one worker owns a device stream; a dead worker's devices wait this "
        "long for another (at most a day: Redis refuses a lease of 2^63 ms or more, and "
        "1e19 left every device's frames undecoded, a traceback logged at each try)",
    )  # fmt: skip
    heartbeat_s: float = Field(
        2.0, ge=MIN_HEARTBEAT_S,
        description="each worker beats, renews its device leases and touches its jobs this "
        "often (at least 0.1 s: each beat is fsynced Redis writes, and at 1e-9 a worker sent "
        "800 commands a second while /health/ready, which counts beats younger than three "
        "heartbeats, found no worker)",
    )  # fmt: skip
    redis_timeout_s: float = Field(
        2.0, ge=0.1, le=60,
        description="longest the API waits for one Redis reply before answering 503 (at "
        "least 0.1 s: a reply can take milliseconds, a write waits for the embedded "
        "Redis's fsync, and at 1 ms 18 of 200 reads of a job answered 503 on an idle host)",
    )  # fmt: skip
    stream_exr_compression: Literal[tuple(EXR_COMPRESSIONS)] = Field(  # type: ignore[valid-type]
        STREAM_EXR_COMPRESSION,
        description="EXR compression of live device frames: none (fastest) or zip (smaller)",
    )
    stream_processes: int | None = Field(
        None,
        ge=1,
        le=MAX_STREAM_POOL_PROCESSES,
        description="processes decoding one device stream's frames in independent mode, "
        "results kept in stream order; unset: one per core (at most 8); 1: in the worker; "
        "at most 256 (1e19 stopped each worker at start with a traceback, 2e9 started "
        "processes by the hundred)",
    )
    result_retention_s: float = Field(
        7 * 24 * 3600.0, gt=0, le=MAX_RESULT_RETENTION_S,
        description="seconds a finished job's record and results are kept (at most 100 "
        "years: Redis expires a record by a whole number of seconds, and a longer or "
        "infinite retention failed every finished job)",
    )  # fmt: skip
    idempotency_ttl_s: float = Field(
        24 * 3600.0, ge=1, le=MAX_RESULT_RETENTION_S,
        description="seconds an Idempotency-Key is remembered after its job was queued: a "
        "request repeating it within that time gets that job instead of a new one, unless "
        "MCAM_RESULT_RETENTION_S has removed the job",
    )  # fmt: skip
    dataset_max_pairs: int = Field(
        DEFAULT_MAX_PAIRS, gt=0,
        description="bracketed reference pairs kept per device; the oldest are removed",
    )  # fmt: skip
    dataset_max_bytes: int = Field(
        DEFAULT_MAX_BYTES, gt=0,
        description="bytes of bracketed reference pairs kept per device; the oldest are removed",
    )  # fmt: skip

    @field_validator("host")
    @classmethod
    def _named_host(cls, value: str) -> str:
        """An empty host (``--host ""``, or ``--host "$HOST"`` with HOST unset) made
        uvicorn listen on every interface, where an empty ``MCAM_HOST`` means the
        default, this machine alone: the API was open to the network unasked. Spaces
        around an address are dropped (``MCAM_HOST="127.0.0.1 "`` in ``.env``), as of a
        number: they stopped the service with "cannot listen on 127.0.0.1 :8000 (Name or
        service not known)", the space unseen."""
        if value.strip():
            return value.strip()
        raise ValueError(
            "is empty: give an address to listen on (127.0.0.1: this machine only; "
            "0.0.0.0 or '::': every interface), or leave it out for 127.0.0.1"
        )

    @field_validator("data_dir", "accuracy_report")
    @classmethod
    def _home_expanded(cls, value: Path | None) -> Path | None:
        """A path beginning ``~`` or ``~user`` is in that home folder, as a shell reads
        it: ``.env``, docker's ``env_file`` and systemd's ``EnvironmentFile`` pass it on
        as it is, and ``MCAM_DATA_DIR=~/data`` put the data in a folder named ``~`` of
        the working folder, while ``mcam serve`` said the key was stored in
        ``~/data/api_keys``."""
        if value is None:
            return None
        try:
            return value.expanduser()
        except RuntimeError:
            raise ValueError(
                f"begins with {value.parts[0]!r}, the home of no user of this machine: "
                "give the folder's full path"
            ) from None

    @field_validator("redis_url")
    @classmethod
    def _usable_redis_url(cls, value: str | None) -> str | None:
        """A URL of the wrong form stopped ``mcam api`` and ``mcam serve`` after their
        start with a traceback of 89 lines (exit 3), ``mcam worker`` with redis-py's."""
        problem = None if value is None else url_problem(value)
        if problem:
            raise ValueError(f"{problem}; or unset MCAM_REDIS_URL for the embedded Redis")
        return value

    @field_validator("max_upload_bytes")
    @classmethod
    def _upload_fits_the_disk(cls, value: int, info: ValidationInfo) -> int:
        """``/health/ready`` wants room for one upload on the data dir's disk: a limit
        past the whole disk started a service that was never ready."""
        data_dir = info.data.get("data_dir")
        if data_dir is None:
            return value
        folder = nearest_folder(data_dir)
        total = shutil.disk_usage(folder).total
        if value <= total:
            return value
        raise ValueError(
            f"is more than the whole disk of the data dir holds ({folder}: {total} bytes), "
            "and /health/ready wants room for one upload there, so the service would never "
            "be ready; lower MCAM_MAX_UPLOAD_BYTES or move MCAM_DATA_DIR to a larger disk"
        )

    @field_validator("heartbeat_s")
    @classmethod
    def _beats_within_lease(cls, value: float, info: ValidationInfo) -> float:
        """Refused here, not only by the worker: ``mcam serve`` and ``mcam api`` would
        otherwise accept jobs for workers that exit at start, over and over."""
        lease_ms, idle_ms = info.data.get("device_lease_ms"), info.data.get("claim_idle_ms")
        if lease_ms is None or idle_ms is None:
            return value
        problem = heartbeat_problem(value, lease_ms, idle_ms)
        if problem:
            raise ValueError(problem)
        return value

    @field_validator("default_decoder")
    @classmethod
    def _known_decoder(cls, value: str) -> str:
        """An unknown default would start a service that blames every client naming no
        decoder (422 'unknown decoder') for the operator's setting."""
        try:
            resolve(value)
        except McamError as exc:
            raise ValueError(exc.message) from None
        return value

    @field_validator("accuracy_report")
    @classmethod
    def _report_gives_figures(cls, value: Path | None) -> Path | None:
        """A report named but missing, unreadable or incomplete would leave those
        decoders without figures, with only a log line to say why."""
        problem = None if value is None else report_problem(value)
        if problem:
            raise ValueError(
                f"{problem}: name the accuracy.json that python -m bench.accuracy wrote "
                "(readable by the service), or unset it to use the repository's "
                "bench/results/accuracy.json"
            )
        return value

    @field_validator("redis_maxmemory")
    @classmethod
    def _room_beyond_the_queue(cls, value: int, info: ValidationInfo) -> int:
        """The embedded Redis must hold more than the queue's codes (an external one
        keeps its own maxmemory, and this setting is not used)."""
        queue_bytes = info.data.get("jobs_max_bytes")
        if info.data.get("redis_url") or queue_bytes is None or value > queue_bytes:
            return value
        raise ValueError(
            f"must exceed MCAM_JOBS_MAX_BYTES ({queue_bytes}), the bytes of codes the queue "
            "may hold, with room for device frames and job records besides, so that a full "
            "queue answers 503 queue_full before Redis fills up; raise it or lower "
            "MCAM_JOBS_MAX_BYTES"
        )

    @model_validator(mode="after")
    def _room_for_the_largest_upload(self) -> Settings:
        """The embedded Redis must take the largest upload when it holds nothing else: a
        smaller maxmemory started a service whose readiness never passed and whose
        largest uploads got 503 store_full, with Retry-After, on an empty queue."""
        room = upload_room(self) + EMPTY_REDIS_BYTES
        if self.redis_url or self.redis_maxmemory >= room:
            return self
        raise ValueError(
            f"MCAM_REDIS_MAXMEMORY ({self.redis_maxmemory}) is below the {room} bytes the "
            "embedded Redis needs to take the largest upload (Redis holds its codes twice "
            "while it takes them, and 2 MiB of its own): raise MCAM_REDIS_MAXMEMORY or lower "
            "the largest upload (MCAM_MAX_PIXELS, MCAM_MAX_VIDEO_SAMPLES, MCAM_JOBS_MAX_BYTES, "
            "MCAM_MAX_QUEUED_BYTES_PER_KEY)"
        )


def nearest_folder(path: Path) -> Path:
    """``path`` if it exists, else its nearest parent that does (where it would be made)."""
    return next(folder for folder in (path, *path.parents) if folder.exists())


def largest_upload_codes(settings: Settings) -> int:
    """Bytes of codes of the largest job an upload can queue: a frame of
    ``MCAM_MAX_PIXELS`` RGB pixels, or a video of ``MCAM_MAX_VIDEO_SAMPLES`` code values
    (``MCAM_MAX_VIDEO_FRAMES`` such frames at most), 2 bytes a code value (16-bit
    codes), and no more than one key's jobs may hold in the queue
    (``MCAM_MAX_QUEUED_BYTES_PER_KEY``) nor the queue itself (``MCAM_JOBS_MAX_BYTES``)."""
    frame = 3 * settings.max_pixels
    video = min(settings.max_video_samples, settings.max_video_frames * frame)
    return min(2 * max(frame, video), settings.max_queued_bytes_per_key,
               settings.jobs_max_bytes)  # fmt: skip


def upload_room(settings: Settings) -> int:
    """Bytes Redis must have free below its maxmemory for ``/health/ready``'s ``queue``
    check to pass: what the largest upload needs there while Redis takes it (its codes
    from :func:`largest_upload_codes`; :func:`worker.redis_memory.submit_room`: twice
    them, up to 1 MiB more, and 64 KiB), so that a load balancer stops sending uploads
    before one gets 503 ``store_full``."""
    return submit_room(largest_upload_codes(settings))


def unknown_variables(names: Iterable[str], source: str) -> list[str]:
    """One problem for each ``MCAM_*`` name among ``names`` that is no setting, found in
    ``source`` (words for where it was set), with the setting it most resembles."""
    known = [PREFIX + field.upper() for field in Settings.model_fields]
    problems = []
    for name in names:
        if name.upper().startswith(PREFIX) and name.upper() not in known:
            close = get_close_matches(name.upper(), known, n=1)
            hint = f"did you mean {close[0]}? " if close else ""
            problems.append(
                f"{name} ({source}) is no setting: {hint}correct its name or remove it "
                "(README lists the settings)"
            )
    return problems


def env_file_bindings(env_file: Path) -> list[Binding]:
    """The statements of ``env_file`` as python-dotenv reads them; none when there is
    nothing of that name. :class:`InvalidInputError` when it is not UTF-8 or cannot be
    read (a folder: pydantic-settings skipped one without a word, as docker makes of a
    bind mount whose file is missing)."""
    if not env_file.exists():
        return []
    try:
        text = env_file.read_text(encoding=ENV_FILE_ENCODING)
    except UnicodeDecodeError as exc:
        raise InvalidInputError(
            f"{env_file} is not {ENV_FILE_ENCODING} text (byte {exc.start} is "
            f"{exc.object[exc.start]:#04x}): save it as {ENV_FILE_ENCODING}"
        ) from None
    except OSError as exc:
        raise InvalidInputError(
            f"cannot read {env_file} ({exc.strerror}): make it a file of NAME=value lines "
            "that the service's user may read, or remove it"
        ) from None
    return list(parse_stream(io.StringIO(text)))


def env_file_problems(bindings: list[Binding], env_file: Path) -> list[str]:
    """What is wrong with the statements of ``env_file``: each line python-dotenv cannot
    read (it logged "could not parse statement starting at line N" and dropped the line,
    a setting in it included, and the service ran without it), then each ``MCAM_*``
    name that is no setting."""
    problems = [
        f"line {binding.original.line} of {env_file} is not NAME=value: correct it (quote "
        "a value with spaces or a quote in it) or begin it with # to make it a comment"
        for binding in bindings
        if binding.error
    ]
    names = [binding.key for binding in bindings if binding.key is not None]
    return problems + unknown_variables(names, str(env_file))


def overridden_settings(environ: Mapping[str, str], bindings: list[Binding]) -> list[str]:
    """The ``MCAM_*`` names of ``bindings`` (``.env``) that ``environ`` gives another,
    non-empty value: the environment's is used, and the line of ``.env`` is not."""
    given = {name.upper(): value for name, value in environ.items() if value}
    return [
        binding.key
        for binding in bindings
        if binding.key is not None
        and binding.key.upper().startswith(PREFIX)
        and binding.key.upper() in given
        and not same_value(binding.key, given[binding.key.upper()], binding.value)
    ]


def same_value(name: str, first: str, second: str | None) -> bool:
    """Whether ``first`` and ``second``, values of the ``MCAM_*`` variable ``name``, mean
    the same; paths are compared as the paths they mean (``mcam serve`` gives its
    workers the data dir's absolute path, where ``.env`` may name it relative to the
    working folder or its home, ``~/data``)."""
    if first == second:
        return True
    field = Settings.model_fields.get(name.upper().removeprefix(PREFIX).lower())
    annotation = None if field is None else field.annotation
    if second is None or Path not in (annotation, *get_args(annotation)):
        return False
    return meant_path(first) == meant_path(second)


def meant_path(text: str) -> Path:
    """The absolute path a path setting's value ``text`` means: ``~`` or ``~user`` at its
    start expanded as :meth:`Settings._home_expanded` does (left as it is where it names
    no user, which the setting itself refuses), resolved against the working folder."""
    path = Path(text)
    with contextlib.suppress(RuntimeError):
        path = path.expanduser()
    return path.resolve()


@cache
def get_settings() -> Settings:
    """The process-wide settings (read once); an ``MCAM_*`` variable that is no setting,
    in the environment or ``.env``, or a ``.env`` that does not decode or parse, is refused
    (:class:`InvalidInputError`). A setting the environment gives another value than
    ``.env`` is logged as a warning (the environment's is used)."""
    env_file = Path(str(Settings.model_config["env_file"]))
    bindings = env_file_bindings(env_file)
    problems = unknown_variables(os.environ, "environment") + env_file_problems(bindings, env_file)
    if problems:
        raise InvalidInputError("; ".join(problems))
    for name in overridden_settings(os.environ, bindings):
        log.warning(
            "%s is set both in the environment and in %s, to other values: the "
            "environment's is used; remove one of them", name, env_file,
        )
    return Settings()
