"""Tests of worker/video_jobs.py: a video job's options, checked before any decoding."""

from __future__ import annotations

import io
import itertools
import threading
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import redis

from models.errors import InvalidInputError, OutputUnderflowError
from models.hdr_io import EXR_COMPRESSIONS
from tests.worker.conftest import PARAMS, count_calls, ramp_frame
from worker import video_output
from worker.deliveries import StreamConsumer
from worker.job_processor import JobContext, JobProcessor
from worker.job_store import JobStore
from worker.jobs import JobState
from worker.metrics import read_metrics
from worker.queue import JobQueue
from worker.redis_keys import JOBS_STREAM
from worker.result_store import RESULTS_DIR, ResultStore
from worker.video_input import WrappedVideo
from worker.video_jobs import DEFAULT_OPTIONS, check_frame_size, run_video_job, video_options
from worker.video_pipeline import decode_video_frames, write_outputs


def test_defaults_give_every_output_and_zip_compressed_exrs() -> None:
    options, outputs = video_options("itoh", {})
    assert outputs == list(DEFAULT_OPTIONS["outputs"])
    assert options.decoder == "itoh" and options.exr_compression == "zip"


@pytest.mark.parametrize("compression", sorted(EXR_COMPRESSIONS))
def test_exr_compression_is_passed_on(compression: str) -> None:
    options, _ = video_options("itoh", {"exr_compression": compression})
    assert options.exr_compression == compression


@pytest.mark.parametrize(
    ("options", "fragment"),
    [
        ({"exr_compression": "lzw"}, "exr_compression must be one of zip, none"),
        ({"colour": "red"}, "unknown video options ['colour']"),
        ({"outputs": []}, "non-empty subset"),
        ({"outputs": ["gif"] * 20_000}, "got 'gif,gif,gif,"),
    ],
)
def test_bad_options_are_refused_with_the_choices(options: dict, fragment: str) -> None:
    with pytest.raises(InvalidInputError) as caught:
        video_options("itoh", options)
    assert fragment in caught.value.message and len(caught.value.message) < 300


@pytest.mark.parametrize(
    ("outputs", "shape", "message"),
    [
        (["hdr10", "sdr"], (3, 64, 20_000),
         "the SDR preview (H.264) takes frames of at most 16384 pixels a side, got 64 x "
         "20000; ask for outputs=hdr10,exr_zip"),
        (["sdr"], (3, 32, 70_000),
         "at most 16384 pixels a side, got 32 x 70000; ask for outputs=exr_zip"),
        (["hdr10", "exr_zip"], (3, 32, 32), "got 32 x 32; ask for outputs=sdr,exr_zip"),
    ],
)  # fmt: skip
def test_mp4_outputs_of_frames_their_encoders_cannot_take_are_refused(
    outputs: list[str], shape: tuple[int, ...], message: str
) -> None:
    """A job was queued for frames wider than libx264 encodes, decoded them all, then
    failed with "Generic error in an external library"; the refusal names the outputs
    frames of that size can have."""
    with pytest.raises(InvalidInputError) as caught:
        check_frame_size(outputs, shape)
    assert caught.value.message.endswith(message)
    check_frame_size(["exr_zip"], shape)


class _RecordingJobs(JobStore):
    """The job store, keeping each progress update it writes."""

    def __init__(self, client: redis.Redis) -> None:
        super().__init__(client)
        self.updates: list[tuple[int, float]] = []

    def update(self, job_id: str, **fields: Any) -> None:
        if "progress" in fields:
            self.updates.append((fields["frames_done"], fields["progress"]))
        super().update(job_id, **fields)


def test_progress_reaches_one_only_when_every_output_is_written(
    client: redis.Redis, queue: JobQueue, data_dir: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Decoding is the first of three stages (then HDR10 and SDR): all frames decoded
    is a third of the job, where it used to read 100% through the encoding."""
    monkeypatch.setattr("worker.video_jobs.CHECK_EVERY_S", 0.0)
    frames = 6
    codes = np.stack([ramp_frame(size=64).codes] * frames)
    job = queue.submit(
        "video", codes, PARAMS, "itoh", {"mode": "independent", "outputs": ["hdr10", "sdr"]}
    )
    jobs = _RecordingJobs(client)
    record = jobs.load(job.id)
    ctx = JobContext(record, jobs, ResultStore(data_dir / RESULTS_DIR, 3600), threading.Event())
    run_video_job(ctx, codes)
    decoded = [fraction for done, fraction in jobs.updates if done == frames]
    assert decoded[0] == pytest.approx(1 / 3)
    assert all(b >= a for a, b in itertools.pairwise(f for _, f in jobs.updates))
    assert jobs.updates[-1] == (frames, 1.0)
    assert len(jobs.updates) > frames  # the encodes report too


def test_hdr10_light_levels_are_measured_as_the_frames_are_decoded(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """MaxCLL and MaxFALL were measured from every frame at the start of the HDR10
    encoding, so its progress (and a cancel) waited there for 40% of its time; they are
    measured as each frame is decoded, and the encoding reports its first frame at once."""
    converted = count_calls(monkeypatch, video_output, "to_nits")
    frames = 6
    video = WrappedVideo(np.stack([ramp_frame(size=64).codes] * frames), PARAMS)
    options, outputs = video_options("itoh", {"outputs": ["hdr10"]})
    seen: dict[str, list[int]] = {"decode": [], "hdr10": []}

    def progress(stage: str, _done: int, _total: int) -> None:
        seen[stage].append(len(converted))

    decoded = decode_video_frames(video, options, progress)
    levels = write_outputs(decoded, video, {"hdr10": io.BytesIO()}, options, progress)
    assert seen["hdr10"][0] - seen["decode"][-1] == 1  # the first frame's, as it is encoded
    assert levels["hdr10"]["max_cll"] == video_output.light_levels(
        decoded.irradiance, options.hdr10
    ).max_cll


def test_exr_frames_that_cannot_be_stored_fail_the_job_at_the_first_such_frame(
    client: redis.Redis, queue: JobQueue, data_dir: Path
) -> None:
    """An all-dark clip at gain 1e6 in half floats: its x / gain (2e-9) is stored as 0
    from frame 0 on (whatever W, a video is not refused when it is sent, as W > 0 would
    keep it). The job decoded all its frames, then failed on frame 0."""
    frames = 6
    codes = np.zeros((frames, 64, 64), np.uint8)
    params = PARAMS.model_copy(update={"gain": 1e6})
    options = {"outputs": ["hdr10", "exr_zip"], "half": True}
    job = queue.submit("video", codes, params, "itoh", options)
    jobs = _RecordingJobs(client)
    ctx = JobContext(
        jobs.load(job.id), jobs, ResultStore(data_dir / RESULTS_DIR, 3600), threading.Event()
    )
    with pytest.raises(OutputUnderflowError, match="^[0-9]+ nonzero pixels of the video frame 0"):
        run_video_job(ctx, codes)
    assert jobs.updates == []


def test_a_videos_decode_counts_in_the_histogram_as_its_frames(
    client: redis.Redis, queue: JobQueue, data_dir: Path
) -> None:
    """mcam_decode_seconds is the time to decode one frame: a 6-frame video's whole
    decode was one sample."""
    frames = 6
    codes = np.stack([ramp_frame(size=64).codes] * frames)
    job = queue.submit("video", codes, PARAMS, "itoh",
                       {"mode": "independent", "outputs": ["exr_zip"]})
    store = ResultStore(data_dir / RESULTS_DIR, 3600)
    processor = JobProcessor(client, store, max_deliveries=3, stop=threading.Event())
    consumer = StreamConsumer(client, JOBS_STREAM, "w-j0", max_deliveries=3)
    [delivery] = consumer.read_new(block_ms=None)
    processor.handle(consumer, delivery)
    assert queue.get(job.id).state is JobState.SUCCEEDED
    histograms = {f.name: f.samples[0] for f in read_metrics(client) if f.kind == "histogram"}
    assert histograms["decode_seconds"].count == frames
    assert histograms["encode_seconds"].count == histograms["total_seconds"].count == 1
    decode_ns = queue.get(job.id).timings_ns["decode"]
    assert histograms["decode_seconds"].value == pytest.approx(decode_ns / 1e9)
