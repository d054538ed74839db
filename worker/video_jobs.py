"""The worker's ``video`` jobs: T wrapped frames in, HDR10 / SDR / EXR-sequence files out.

``run_video_job`` is the handler :mod:`worker.job_processor` names for job kind
``video``. The job record carries the spatial decoder and the sensor parameters;
its ``options`` (see :func:`video_options`) pick the decoding mode, the outputs
and the exposure scaling. Frames are decoded as one stream (the first frame is a
keyframe), up to :data:`CHUNK_FRAMES` at a time in the job's child process
(:meth:`worker.job_processor.JobContext.run`); ``frames_done`` counts decoded frames
and ``progress`` the share of all stages (decoding, then each output's encoding); a
cancellation or a stopping worker ends the job between frames of any stage (a stopped
job is handed back and redone from its first frame by the next worker, so temporal
state never spans workers).
"""

from __future__ import annotations

import io
import math
import time
from collections.abc import Sequence
from functools import partial
from typing import Any

import numpy as np
from numpy.typing import NDArray

from models.errors import InvalidInputError, echo
from models.hdr_io import DEFAULT_EXR_COMPRESSION, EXR_COMPRESSIONS
from worker.job_processor import JobContext, JobOutcome
from worker.temporal_config import TemporalConfig
from worker.video_input import WrappedVideo
from worker.video_output import (
    MAX_MP4_SIDES,
    REFERENCE_WHITE,
    Hdr10Settings,
    mp4_size_problem,
    padding_note,
)
from worker.video_pipeline import OUTPUTS, VideoOptions, decode_video_frames, write_outputs

#: Result file name of each output.
VIDEO_FILES: dict[str, str] = {
    "hdr10": "video-hdr10.mp4",
    "sdr": "video-sdr.mp4",
    "exr_zip": "frames-exr.zip",
}
#: Most frames decoded per call of the job's child process (fewer when frames are slow:
#: about a second's worth, :func:`worker.video_pipeline.decode_video_frames`): each
#: call carries the stream's state there and back (its previous ``u``: 0.5 MB at
#: 256x256), and progress is reported between calls.
CHUNK_FRAMES = 8
#: While outputs are encoded, progress is recorded (and a cancel looked for) at most
#: this often (s).
CHECK_EVERY_S = 0.25
#: The options a video job takes, with their defaults.
DEFAULT_OPTIONS: dict[str, Any] = {
    "mode": "temporal",
    "outputs": list(OUTPUTS),
    "fps": 30.0,
    "white_level": 1.0,
    "reference_white": REFERENCE_WHITE,
    "keyframe_interval": TemporalConfig.keyframe_interval,
    "half": False,
    "exr_compression": DEFAULT_EXR_COMPRESSION,
    "keyframes": [],
}


def video_options(decoder: str, options: dict[str, Any]) -> tuple[VideoOptions, list[str]]:
    """The decode/render options and the outputs of a job (unknown options refused)."""
    unknown = set(options) - set(DEFAULT_OPTIONS)
    if unknown:
        raise InvalidInputError(f"unknown video options {sorted(unknown)}")
    values = DEFAULT_OPTIONS | options
    outputs = list(values["outputs"])
    bad = [name for name in outputs if name not in OUTPUTS]
    if bad or not outputs:
        raise InvalidInputError(
            f"video outputs must be a non-empty subset of {', '.join(OUTPUTS)}, got "
            f"{echo(','.join(map(str, outputs)))}"
        )
    if values["exr_compression"] not in EXR_COMPRESSIONS:
        raise InvalidInputError(
            f"exr_compression must be one of {', '.join(EXR_COMPRESSIONS)}, "
            f"got {values['exr_compression']!r}"
        )
    return (
        VideoOptions(
            mode=values["mode"],
            decoder=decoder,
            temporal=TemporalConfig(keyframe_interval=int(values["keyframe_interval"])),
            hdr10=Hdr10Settings(
                fps=float(values["fps"]),
                white_level=float(values["white_level"]),
                reference_white=float(values["reference_white"]),
            ),
            half=bool(values["half"]),
            exr_compression=str(values["exr_compression"]),
            keyframes=frozenset(int(i) for i in values["keyframes"]),
            check_exr="exr_zip" in outputs,
            measure_light="hdr10" in outputs,
        ),
        outputs,
    )


def check_frame_size(outputs: list[str], shape: tuple[int, ...]) -> None:
    """Refuse an MP4 output (HDR10, SDR) for frames (T x H x W[x C]) of a size its
    encoder does not take, before a job decodes them all, naming the outputs that
    frames of that size can have."""
    problems = {name: mp4_size_problem(name, shape[1], shape[2]) for name in MAX_MP4_SIDES}
    refused = [name for name in outputs if problems.get(name)]
    if refused:
        fitting = ",".join(name for name in OUTPUTS if not problems.get(name))
        raise InvalidInputError(f"{problems[refused[0]]}; ask for outputs={fitting}")


def video_warnings(
    noticed: Sequence[str], outputs: list[str], shape: tuple[int, ...]
) -> list[str]:
    """A video job's ``warnings``: what reading or recording its frames ``noticed``,
    then, when its frames (T x H x W[x C]) have an odd side and ``outputs`` hold an MP4,
    what the MP4 videos are padded to (:func:`worker.video_output.padding_note`)."""
    padded = padding_note(outputs, shape[1], shape[2])
    return [*noticed, padded] if padded else list(noticed)


class StageProgress:
    """A video job's progress through its stages (decoding, then each output), each
    weighing the same: the job shows 100% only once its last output is written, not
    once its frames are decoded. Between frames it also checks for a cancel or a
    stopping worker, at most every :data:`CHECK_EVERY_S` while encoding (each check is a
    Redis round trip, an encoded frame a few ms)."""

    def __init__(self, ctx: JobContext, stages: list[str], frames: int) -> None:
        self.ctx, self.stages, self.frames = ctx, stages, max(frames, 1)
        self.checked = -math.inf

    def __call__(self, stage: str, done: int, _total: int) -> None:
        now = time.monotonic()
        if stage != "decode" and done < self.frames and now - self.checked < CHECK_EVERY_S:
            return
        self.checked = now
        work = self.stages.index(stage) * self.frames + done
        decoded = done if stage == "decode" else self.frames
        self.ctx.progress(decoded, work / (len(self.stages) * self.frames))
        self.ctx.check_all()


def run_video_job(ctx: JobContext, codes: NDArray[np.unsignedinteger]) -> JobOutcome:
    """Decode the job's frames, write its outputs to the result store."""
    record = ctx.record
    options, outputs = video_options(record.decoder, record.options)
    video = WrappedVideo(codes, record.params)

    progress = StageProgress(ctx, ["decode", *outputs], video.frames)
    start = time.perf_counter_ns()
    decoded = decode_video_frames(
        video, options, progress, run=partial(ctx.run, hand_back=True), chunk=CHUNK_FRAMES
    )
    decoded_ns = time.perf_counter_ns()
    buffers = {name: io.BytesIO() for name in outputs}
    facts = write_outputs(decoded, video, dict(buffers), options, progress)
    ctx.check()
    results = {name: ctx.write(VIDEO_FILES[name], buffers[name].getvalue()) for name in outputs}
    return JobOutcome(
        results=results,
        timings_ns={"decode": decoded_ns - start, "encode": time.perf_counter_ns() - decoded_ns},
        info={"mode": options.mode, "decoder": record.decoder, **decoded.summary(), **facts},
    )
