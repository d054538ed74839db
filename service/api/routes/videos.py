"""``POST /v1/videos``: queue a wrapped video; ``GET /v1/videos/{id}/result``: its files.

The upload is a multi-page TIFF, a ``.npy`` of shape T x H x W[x C] or a zip of PNG
frames (see ``worker/video_input.py``). The job (``GET /v1/jobs/{id}``) reports
progress as frames decoded of frames total; when it succeeded its outputs are
downloaded by name: ``hdr10`` (HEVC Main10 PQ MP4), ``sdr`` (H.264 preview MP4),
``exr_zip`` (one EXR per frame).
"""

from __future__ import annotations

from typing import Annotated, Any, Literal

from fastapi import APIRouter, Query, Request, Response
from pydantic import BaseModel, ConfigDict, Field

from models.errors import UnsupportedFormatError
from models.file_magic import VIDEO_MAGICS, format_by_content, named_format
from models.hdr_io import DEFAULT_EXR_COMPRESSION, EXR_COMPRESSIONS
from service.api.deps import ReadKey, StateDep, SubmitKey
from service.api.downloads import stored_file
from service.api.errors import ApiError
from service.api.idempotency import IdempotencyHeader, queued_job
from service.api.routes.jobs import JOB_ERRORS, succeeded
from service.api.schemas import (
    UPLOAD_ERRORS,
    JobAccepted,
    accepted_response,
    error_response,
    stored_file_responses,
    upload_body,
)
from service.api.state import ServiceState
from service.api.uploads import SensorFields, Upload
from service.core.security import ApiKey
from worker.idempotency import IdempotentSubmit
from worker.jobs import JobRecord
from worker.outputs import check_video_storable
from worker.temporal_config import MAX_KEYFRAME_INTERVAL, TemporalConfig
from worker.video_input import VIDEO_ALIASES, VideoLimits, decode_video, not_a_video
from worker.video_jobs import VIDEO_FILES, check_frame_size, video_options, video_warnings
from worker.video_output import (
    FPS_RANGE,
    REFERENCE_WHITE,
    REFERENCE_WHITE_RANGE,
    WHITE_LEVEL_RANGE,
)
from worker.video_pipeline import OUTPUTS

router = APIRouter(prefix="/v1/videos", tags=["videos"])

_MEDIA = {"hdr10": "video/mp4", "sdr": "video/mp4", "exr_zip": "application/zip"}


class VideoOptionFields(BaseModel):
    """How a video is decoded and rendered (uploads and live recordings)."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    decoder: str | None = Field(None, description="spatial decoder (GET /v1/decoders)")
    mode: Literal["independent", "temporal"] = Field(
        "temporal", description="frame by frame, or unwrapped along time with fallbacks"
    )
    outputs: str = Field(
        ",".join(OUTPUTS), description=f"comma-separated subset of {', '.join(OUTPUTS)}"
    )
    fps: float = Field(
        30.0, ge=FPS_RANGE[0], le=FPS_RANGE[1],
        description="frame rate of the videos (23.976, 29.97, 59.94: the NTSC rates)",
    )  # fmt: skip
    white_level: float = Field(
        1.0, ge=WHITE_LEVEL_RANGE[0], le=WHITE_LEVEL_RANGE[1],
        description="x (wrap units) shown at the reference white",
    )  # fmt: skip
    reference_white: float = Field(
        REFERENCE_WHITE, ge=REFERENCE_WHITE_RANGE[0], le=REFERENCE_WHITE_RANGE[1],
        description="cd/m^2 (default: ITU-R BT.2408)",
    )  # fmt: skip
    keyframe_interval: int = Field(
        TemporalConfig.keyframe_interval, ge=0, le=MAX_KEYFRAME_INTERVAL,
        description="temporal: spatial keyframe period in frames (0: none but the first)",
    )  # fmt: skip
    half: bool = Field(
        False, description="EXR frames as half floats (values under 6.1e-5 kept to 3e-8)"
    )
    exr_compression: Literal[tuple(EXR_COMPRESSIONS)] = Field(  # type: ignore[valid-type]
        DEFAULT_EXR_COMPRESSION,
        description="lossless compression of the EXR frames: zip (smaller) or none",
    )

    def video_job_options(self) -> dict[str, Any]:
        """The options of the video job (see ``worker.video_jobs.video_options``)."""
        return {
            "mode": self.mode,
            "outputs": list(
                dict.fromkeys(name.strip() for name in self.outputs.split(",") if name.strip())
            ),
            "fps": self.fps,
            "white_level": self.white_level,
            "reference_white": self.reference_white,
            "keyframe_interval": self.keyframe_interval,
            "half": self.half,
            "exr_compression": self.exr_compression,
        }


class VideoFields(SensorFields, VideoOptionFields):
    """Parameters of ``POST /v1/videos``."""

    format: Literal["tiff", "npy", "zip"] | None = Field(
        None, description="video file format; default: from the file name or its first bytes. "
        "A TIFF, npy or zip is read as what its first bytes show, whatever this or the name "
        "says",
    )


def sniff_video_format(upload: Upload, declared: str | None) -> str:
    """The video format: declared, else the file name's suffix, else the leading bytes.
    A TIFF, npy or zip is decoded as what its leading bytes show whatever its name says
    (:func:`worker.video_input.decode_video`)."""
    fmt = (
        declared
        or named_format(upload.filename, VIDEO_ALIASES)
        or format_by_content(upload.data, VIDEO_MAGICS)
    )
    if fmt is not None:
        return fmt
    other = not_a_video(upload.data)
    raise UnsupportedFormatError(
        "cannot tell the video's format: send a multi-page .tiff, a .npy (T x H x W[x C]) "
        f"or a .zip of PNG frames{'' if other is None else f'; this file is {other}'}"
    )


def submit(
    state: ServiceState,
    upload: Upload,
    fields: VideoFields,
    key: ApiKey,
    once: IdempotentSubmit | None = None,
) -> JobRecord:
    """Decode the upload, check the options and queue the job for ``key`` (under the
    request's idempotency key, ``once``, if any), with what the decode noticed, and that
    its MP4 videos are padded to even sides, as the job's ``warnings``."""
    settings = state.settings
    fmt = sniff_video_format(upload, fields.format)
    limits = VideoLimits(
        settings.max_pixels, settings.max_video_frames, settings.max_video_samples
    )
    video = decode_video(upload.data, fmt, fields.sensor_overrides(), limits)
    decoder = fields.decoder or settings.default_decoder
    options = fields.video_job_options()
    video_options(decoder, options)
    check_frame_size(options["outputs"], video.codes.shape)
    if "exr_zip" in options["outputs"]:
        check_video_storable(video.codes, video.params, options)
    return state.queue.submit(
        "video", video.codes, video.params, decoder, options, owner=key.id,
        warnings=video_warnings(video.warnings, options["outputs"], video.codes.shape),
        idempotency=once,
    )


@router.post(
    "",
    summary="Decode a wrapped video into HDR10 / SDR / EXR-sequence files (asynchronous job)",
    status_code=202,
    response_model=JobAccepted,
    responses={202: {"model": JobAccepted, "description": "queued"}, **UPLOAD_ERRORS},
    openapi_extra=upload_body(VideoFields, "a wrapped video (.tiff pages, .npy, .zip of PNGs)"),
)
async def post_video(
    request: Request,
    query: Annotated[VideoFields, Query()],
    state: StateDep,
    key: SubmitKey,
    idempotency_key: IdempotencyHeader = None,
) -> Response:
    """Queue a wrapped video; poll ``GET /v1/jobs/{id}`` for progress (frames done). A
    repeat of a request with its ``Idempotency-Key`` is answered with its job
    (:mod:`service.api.idempotency`)."""
    record = await queued_job(request, query, VideoFields, state, key, idempotency_key, submit)
    return accepted_response(record)


@router.get(
    "/{job_id}/result",
    summary="A finished video job's file: hdr10, sdr or exr_zip",
    response_class=Response,
    responses={
        200: {"content": {"video/mp4": {}, "application/zip": {}}},
        409: error_response(
            "the job has not succeeded (job_not_finished, job_failed, job_cancelled), is "
            "not a video (not_a_video_job) or does not make that output (output_not_made); "
            "the last two also while it is queued or running"
        ),
        **stored_file_responses("the file"),
        **JOB_ERRORS,
    },
)
def get_video_result(
    job_id: str,
    state: StateDep,
    _: ReadKey,
    output: Annotated[
        Literal["hdr10", "sdr", "exr_zip"], Query(description="which file")
    ] = "hdr10",
) -> Response:
    """The output file of a succeeded video job. A job that is not a video, or an output
    that a queued or running video job will not make, is refused at once
    (``not_a_video_job``, ``output_not_made``; not ``job_not_finished``)."""
    record = state.queue.get(job_id)
    if record.kind != "video":
        raise ApiError(
            409, "not_a_video_job",
            f"job {job_id} is a {record.kind} job, not a video; fetch its result from "
            f"/v1/jobs/{job_id}/result",
        )  # fmt: skip
    if not record.state.finished:
        planned = video_options(record.decoder, record.options)[1]
        if output not in planned:
            raise output_not_made(record, output, planned)
    record = succeeded(record)
    if output not in record.results:
        raise output_not_made(record, output, sorted(record.results))
    return stored_file(state.store, record.results[output], _MEDIA[output],
                       f"{job_id}-{VIDEO_FILES[output]}")


def output_not_made(record: JobRecord, output: str, outputs: list[str]) -> ApiError:
    """The 409 for ``output`` of the video job ``record``, which makes only ``outputs``
    (made them, once it finished)."""
    done = record.state.finished
    return ApiError(
        409, "output_not_made",
        f"video job {record.id} {'did' if done else 'will'} not make {output!r}; it "
        f"{'made' if done else 'makes'}: {', '.join(outputs)} (choose the outputs when "
        "submitting)",
    )  # fmt: skip
