"""A wrapped video to its outputs: decode every frame, then write the requested files.

Used by ``mcam video`` and by the worker's video jobs. Decoding follows
:mod:`worker.temporal` (``independent`` or ``temporal``); outputs are those of
:mod:`worker.video_output`:

- ``hdr10``: HEVC Main10 PQ video of ``x`` (wrap units; ``white_level`` x is shown at
  the reference white);
- ``sdr``: the tonemapped H.264 preview;
- ``exr_zip``: one EXR per frame, scene-referred (``x / gain``) when the gain is
  known, else wrap units, with the header ``mcam reconstruct`` writes of single frames
  (sensor parameters, decoder, units) and the frame's stream facts (mode, keyframe,
  path shares).

``progress(stage, done, total)`` is called after each frame of each stage
(``decode``, then each output in order).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from functools import lru_cache
from typing import Any

import numpy as np
from numpy.typing import NDArray

from models.errors import InvalidInputError, naming
from models.exr_header import reconstruction_attributes, stream_attributes
from models.formation import SensorParams
from models.hdr_io import DEFAULT_EXR_COMPRESSION
from worker.stream_state import FrameDecode, StreamState
from worker.temporal import StreamDecoder
from worker.temporal_config import TemporalConfig
from worker.video_input import WrappedVideo
from worker.video_output import (
    FrameLight,
    Hdr10Settings,
    Target,
    check_exr_frame,
    check_exr_sequence,
    clip_light,
    exr_sequence_zip,
    frame_light,
    write_hdr10,
    write_sdr_preview,
)

OUTPUTS: tuple[str, ...] = ("hdr10", "sdr", "exr_zip")
StageProgress = Callable[[str, int, int], None]


@dataclass(frozen=True)
class VideoOptions:
    """How to decode and render a video: ``mode`` and spatial ``decoder``, the temporal
    knobs, HDR10 settings (frame rate, exposure scaling), half-float EXRs and their
    compression (:data:`models.hdr_io.EXR_COMPRESSIONS`).
    ``keyframes``: indices of frames decoded as after a DISCONT (a live recording's
    reconnects and sequence gaps). ``check_exr``: refuse each frame whose EXR frame
    cannot be stored as soon as it is decoded (:func:`worker.video_output.check_exr_frame`;
    the video has EXR frames): an all-dark clip at gain 1e6 in half floats, stored as 0
    from its first frame, failed only once its last frame was decoded. ``measure_light``:
    measure each frame's light levels as it is decoded (:func:`worker.video_output.frame_light`;
    the video has an HDR10 output): measured once all were decoded, at the start of the
    HDR10 encoding, they held its progress (and a cancel) for 40% of its time (0.34 of
    0.83 s a frame at 1920 x 1080)."""

    mode: str = "temporal"
    decoder: str = "itoh"
    temporal: TemporalConfig = field(default_factory=TemporalConfig)
    hdr10: Hdr10Settings = field(default_factory=Hdr10Settings)
    half: bool = False
    exr_compression: str = DEFAULT_EXR_COMPRESSION
    keyframes: frozenset[int] = frozenset()
    check_exr: bool = False
    measure_light: bool = False


@dataclass
class DecodedVideo:
    """Per-frame reconstructions ``x`` (wrap units) and decode facts, the spatial
    decoder's ``{"decoder": name, "version": version}``, and each frame's light levels
    when they were measured (``VideoOptions.measure_light``). No output needs the W maps,
    so they are not kept (8 bytes a sample: 40% of a video job's memory)."""

    irradiance: list[NDArray[np.float64]]
    frames: list[dict[str, Any]]
    decoder: dict[str, str] = field(default_factory=dict)
    lights: list[FrameLight] = field(default_factory=list)

    def add(self, frame: FrameDecode) -> None:
        """Append one decoded frame."""
        self.irradiance.append(frame.irradiance)
        self.frames.append(frame.summary())

    def extend(self, other: DecodedVideo) -> None:
        """Append the frames of ``other``, in order."""
        self.irradiance += other.irradiance
        self.frames += other.frames
        self.lights += other.lights
        self.decoder = other.decoder or self.decoder

    def summary(self) -> dict[str, Any]:
        """Keyframes, mean path shares and mean decode time, for a job record."""
        paths = [frame["paths"] for frame in self.frames]
        return {
            "frames": len(self.frames),
            "keyframes": sum(frame["keyframe"] is not None for frame in self.frames),
            "paths": {name: float(np.mean([p[name] for p in paths])) for name in paths[0]},
            "ms_per_frame": float(
                np.mean([frame["timings_ns"]["total"] for frame in self.frames]) / 1e6
            ),
        }


#: Runs ``function(*args)`` somewhere and returns its result: here, or in a worker job's
#: child process (:meth:`worker.job_processor.JobContext.run`).
Runner = Callable[..., Any]


def run_here(function: Callable[..., Any], *args: Any) -> Any:
    """The default :data:`Runner`: call ``function`` in this process."""
    return function(*args)


@lru_cache(maxsize=8)
def stream_decoder(mode: str, decoder: str, temporal: TemporalConfig) -> StreamDecoder:
    """One :class:`worker.temporal.StreamDecoder` per (mode, decoder, knobs) in a
    process: it keeps no stream's state, so chunks of any video may share it."""
    return StreamDecoder(mode, decoder, temporal)


def decode_chunk(
    options: VideoOptions,
    params: SensorParams,
    codes: NDArray[np.unsignedinteger],
    first: int,
    state: StreamState,
) -> tuple[DecodedVideo, StreamState]:
    """Frames ``first`` .. ``first + len(codes) - 1`` of a video (codes, DN) decoded as one
    stream continuing from ``state``; their results and the state after the last. A frame
    that cannot be decoded (an ``x`` past float64, say), or whose EXR frame cannot be
    stored (``options.check_exr``), is refused naming its index."""
    decoder = stream_decoder(options.mode, options.decoder, options.temporal)
    spatial = {"decoder": decoder.spatial.name, "version": decoder.spatial.version}
    decoded = DecodedVideo([], [], spatial)
    for index, frame_codes in enumerate(codes, start=first):
        discont = index in options.keyframes
        with naming(f"video frame {index}"):
            decoded.add(decoder.decode(frame_codes, params, state, discont=discont))
        if options.check_exr:
            check_exr_frame(
                decoded.irradiance[-1], index, half=options.half, scene_gain=params.gain
            )
        if options.measure_light:
            decoded.lights.append(frame_light(decoded.irradiance[-1], options.hdr10))
    return decoded, state


def decode_video_frames(
    video: WrappedVideo,
    options: VideoOptions,
    progress: StageProgress | None = None,
    *,
    run: Runner = run_here,
    chunk: int = 1,
    chunk_s: float = 1.0,
) -> DecodedVideo:
    """Decode every frame of ``video`` in order, as one stream, in calls of ``run`` of at
    most ``chunk`` frames: the first call takes one frame, each next one as many as the
    frames so far suggest fit in ``chunk_s`` seconds (at least one), so that progress,
    reported after each call, advances about every ``chunk_s`` on slow frames too."""
    state = StreamState()
    decoded = DecodedVideo([], [])
    size, first = 1, 0
    start = time.perf_counter()
    while first < video.frames:
        codes = video.codes[first : first + size]
        part, state = run(decode_chunk, options, video.params, codes, first, state)
        decoded.extend(part)
        first += len(codes)
        if progress:
            progress("decode", first, video.frames)
        per_frame_s = (time.perf_counter() - start) / first
        size = max(1, min(chunk, int(chunk_s / max(per_frame_s, 1e-9))))
    return decoded


def write_outputs(
    decoded: DecodedVideo,
    video: WrappedVideo,
    targets: dict[str, Target],
    options: VideoOptions,
    progress: StageProgress | None = None,
) -> dict[str, Any]:
    """Write each requested output (a name of :data:`OUTPUTS` -> path or binary file);
    returns facts about them (HDR10 light levels)."""
    unknown = set(targets) - set(OUTPUTS)
    if unknown:
        raise InvalidInputError(
            f"unknown video outputs {sorted(unknown)}; choose from: {', '.join(OUTPUTS)}"
        )
    total = len(decoded.irradiance)
    gain = video.params.gain
    if "exr_zip" in targets and not options.check_exr:
        # Before any encoding, so a clip that cannot be stored fails; with check_exr its
        # frames were checked as they were decoded (decode_chunk).
        check_exr_sequence(decoded.irradiance, half=options.half, scene_gain=gain)
    facts: dict[str, Any] = {}
    for name, target in targets.items():

        def step(done: int, name: str = name) -> None:
            if progress:
                progress(name, done, total)

        if name == "hdr10":
            measured = clip_light(decoded.lights) if decoded.lights else None
            levels = write_hdr10(decoded.irradiance, target, options.hdr10, step, measured)
            facts["hdr10"] = {
                "max_cll": levels.max_cll, "max_fall": levels.max_fall,
                "clipped_share": round(levels.clipped_share, 6),
            }  # fmt: skip
        elif name == "sdr":
            write_sdr_preview(decoded.irradiance, target, options.hdr10.fps, progress=step)
        else:
            exr_sequence_zip(
                decoded.irradiance, target, half=options.half,
                compression=options.exr_compression,
                attributes=exr_frame_attributes(decoded, video.params, options.mode),
                scene_gain=gain, checked=True, progress=step,
            )  # fmt: skip
    return facts


def exr_frame_attributes(
    decoded: DecodedVideo, params: SensorParams, mode: str
) -> list[dict[str, str]]:
    """The EXR header of each frame: what ``mcam reconstruct`` writes of a frame (sensor
    parameters, decoder, units) and how the stream decoded it (:mod:`models.exr_header`)."""
    return [
        reconstruction_attributes(params, decoded.decoder, f"video frame {index}")
        | stream_attributes(mode, frame)
        for index, frame in enumerate(decoded.frames)
    ]
