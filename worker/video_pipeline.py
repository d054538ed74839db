"""A wrapped video to its outputs: decode every frame, then write the requested files.

Used by ``mcam video`` and by the worker's video jobs. Decoding follows
:mod:`worker.temporal` (``independent`` or ``temporal``); outputs are those of
:mod:`worker.video_output`:

- ``hdr10``: HEVC Main10 PQ video of ``x`` (wrap units; ``white_level`` x is shown at
  the reference white);
- ``sdr``: the tonemapped H.264 preview;
- ``exr_zip``: one EXR per frame, scene-referred (``x / gain``) when the gain is
  known, else wrap units, as ``mcam reconstruct`` writes single frames.

``progress(stage, done, total)`` is called after each frame of each stage
(``decode``, then each output in order).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from models.errors import InvalidInputError
from models.hdr_io import DEFAULT_EXR_COMPRESSION
from worker.stream_state import StreamState
from worker.temporal import StreamDecoder
from worker.temporal_config import TemporalConfig
from worker.video_input import WrappedVideo
from worker.video_output import (
    Hdr10Settings,
    Target,
    exr_sequence_zip,
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
    reconnects and sequence gaps)."""

    mode: str = "temporal"
    decoder: str = "itoh"
    temporal: TemporalConfig = field(default_factory=TemporalConfig)
    hdr10: Hdr10Settings = field(default_factory=Hdr10Settings)
    half: bool = False
    exr_compression: str = DEFAULT_EXR_COMPRESSION
    keyframes: frozenset[int] = frozenset()


@dataclass
class DecodedVideo:
    """Per-frame reconstructions ``x`` (wrap units), W maps and decode facts."""

    irradiance: list[NDArray[np.float64]]
    winding: list[NDArray[np.int64]]
    frames: list[dict[str, Any]]

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


def decode_video_frames(
    video: WrappedVideo, options: VideoOptions, progress: StageProgress | None = None
) -> DecodedVideo:
    """Decode every frame of ``video`` in order, as one stream."""
    decoder = StreamDecoder(options.mode, options.decoder, options.temporal)
    state = StreamState()
    decoded = DecodedVideo([], [], [])
    for index, codes in enumerate(video.codes):
        frame = decoder.decode(codes, video.params, state, discont=index in options.keyframes)
        decoded.irradiance.append(frame.irradiance)
        decoded.winding.append(frame.winding)
        decoded.frames.append(frame.summary())
        if progress:
            progress("decode", index + 1, video.frames)
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
    facts: dict[str, Any] = {}
    for name, target in targets.items():

        def step(done: int, name: str = name) -> None:
            if progress:
                progress(name, done, total)

        if name == "hdr10":
            levels = write_hdr10(decoded.irradiance, target, options.hdr10, step)
            facts["hdr10"] = {"max_cll": levels.max_cll, "max_fall": levels.max_fall}
        elif name == "sdr":
            write_sdr_preview(decoded.irradiance, target, options.hdr10.fps, progress=step)
        else:
            gain = video.params.gain
            frames = decoded.irradiance if gain is None else [x / gain for x in decoded.irradiance]
            exr_sequence_zip(
                frames, target, half=options.half, compression=options.exr_compression
            )
            step(total)
    return facts
