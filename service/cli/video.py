"""``mcam video``: decode a wrapped video into HDR10 video, an SDR preview or EXR frames."""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import Any

from models.errors import InvalidInputError
from service.cli.options import add_exr_compression_flag, add_sensor_flags, sensor_values
from service.cli.output_files import OutputFile, staged_outputs
from worker.outputs import check_video_storable
from worker.queue import check_decoder_supports
from worker.temporal_config import MODES, TemporalConfig
from worker.video_input import read_video
from worker.video_output import (
    FPS_RANGE,
    REFERENCE_WHITE,
    REFERENCE_WHITE_RANGE,
    WHITE_LEVEL_RANGE,
    Hdr10Settings,
    check_mp4_frame_size,
    mp4_size_problem,
    padding_note,
)
from worker.video_pipeline import VideoOptions, decode_video_frames, write_outputs

#: Output suffixes and the output each one means.
SUFFIXES = {".mp4": "hdr10", ".zip": "exr_zip"}
BAR_WIDTH = 30


def register(subparsers: Any) -> None:
    """Add the ``video`` command."""
    parser = subparsers.add_parser(
        "video",
        help="decode a wrapped video (HDR10 HEVC .mp4, EXR-sequence .zip, SDR preview)",
        description="Decode a wrapped video (multi-page .tiff, .npy T x H x W[x C], .zip of "
        "PNG frames) frame by frame (--mode independent) or along time (--mode temporal), "
        "and write an HDR10 video (-o clip.mp4) or an EXR sequence (-o frames.zip).",
    )
    parser.add_argument("video", help="wrapped video: .tiff, .npy or .zip of PNGs")
    parser.add_argument("-o", "--output", required=True, help="clip.mp4 (HDR10) or frames.zip")
    parser.add_argument("--mode", choices=MODES, default="temporal", help="default: temporal")
    parser.add_argument("--decoder", default="itoh", help="spatial decoder (default: itoh)")
    parser.add_argument("--preview", metavar="SDR.mp4", help="also write an SDR H.264 preview")
    parser.add_argument("--exr", metavar="FRAMES.zip", help="also write the EXR sequence")
    parser.add_argument(
        "--fps", type=float, default=30.0,
        help=f"frame rate, {FPS_RANGE[0]:g} to {FPS_RANGE[1]:g} (default: 30); 23.976, 29.97 "
        "and 59.94 are written as the NTSC rates 24000/1001, 30000/1001, 60000/1001",
    )  # fmt: skip
    parser.add_argument(
        "--white-level", type=float, default=1.0,
        help="x (wrap units) shown at the reference white, "
        f"{WHITE_LEVEL_RANGE[0]:g} to {WHITE_LEVEL_RANGE[1]:g} (default: 1)",
    )
    parser.add_argument(
        "--reference-white", type=float, default=REFERENCE_WHITE,
        help=f"cd/m^2 of the reference white, {REFERENCE_WHITE_RANGE[0]:g} to "
        f"{REFERENCE_WHITE_RANGE[1]:g} (default: {REFERENCE_WHITE:g}, ITU-R BT.2408)",
    )
    parser.add_argument(
        "--keyframe-interval", type=int, default=TemporalConfig.keyframe_interval,
        help="temporal mode: decode every Nth frame spatially (0: never; default: "
        f"{TemporalConfig.keyframe_interval})",
    )
    parser.add_argument("--half", action="store_true", help="EXR frames as half floats")
    add_exr_compression_flag(parser)
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    add_sensor_flags(parser, "fill in or override the parameters stored in the video")
    parser.set_defaults(func=run)


def output_files(args: argparse.Namespace) -> dict[str, OutputFile]:
    """The files to write, by output (:data:`worker.video_pipeline.OUTPUTS`)."""
    main = OutputFile(
        "-o", args.output, "the output is an HDR10 video (.mp4) or EXR frames (.zip)",
        tuple(SUFFIXES),
    )  # fmt: skip
    main.check_name()
    kind = SUFFIXES[Path(args.output).suffix.lower()]
    files = {kind: main}
    if args.preview:
        files["sdr"] = OutputFile(
            "--preview", args.preview, "the SDR preview is an H.264 video", (".mp4",)
        )
    if args.exr:
        if kind == "exr_zip":
            raise InvalidInputError(
                f"-o {args.output} already writes the EXR frames; drop --exr {args.exr}, or "
                "write the HDR10 video with -o clip.mp4"
            )
        files["exr_zip"] = OutputFile("--exr", args.exr, "the EXR frames are a zip", (".zip",))
    return files


def check_frame_size(files: dict[str, OutputFile], shape: tuple[int, ...]) -> None:
    """Refuse an MP4 output whose encoder does not take frames of the video's size
    (T x H x W[x C]), before they are decoded, saying what to write instead."""
    height, width = shape[1], shape[2]
    preview = "" if mp4_size_problem("sdr", height, width) else ", with --preview for an SDR video"
    remedies = {
        "hdr10": f"write the EXR frames instead (-o clip.zip{preview})",
        "sdr": "drop --preview, and write the EXR frames (-o clip.zip, or --exr frames.zip)",
    }
    for output, remedy in remedies.items():
        if output in files:
            check_mp4_frame_size(output, height, width, remedy)


def progress_bar(stage: str, done: int, total: int) -> None:
    """Draw ``stage [#####.....] done/total`` on stderr, ending the line when done; when
    stderr is not a terminal (a log, a pipe), only the finished line of each stage."""
    finished = done >= total
    if not (finished or sys.stderr.isatty()):
        return
    filled = BAR_WIDTH * done // max(total, 1)
    bar = "#" * filled + "." * (BAR_WIDTH - filled)
    line = f"{stage:<8} [{bar}] {done}/{total} frames"
    if sys.stderr.isatty():
        print(f"\r{line}", end="\n" if finished else "", file=sys.stderr, flush=True)
    else:
        print(line, file=sys.stderr, flush=True)


def run(args: argparse.Namespace) -> int:
    """Read, decode and write; print a one-line summary."""
    files = output_files(args)
    options = VideoOptions(
        mode=args.mode,
        decoder=args.decoder,
        temporal=TemporalConfig(keyframe_interval=args.keyframe_interval),
        hdr10=Hdr10Settings(
            fps=args.fps, white_level=args.white_level, reference_white=args.reference_white
        ),
        half=args.half,
        exr_compression=args.exr_compression,
        check_exr="exr_zip" in files,
        measure_light="hdr10" in files,
    )
    with staged_outputs(list(files.values()), [args.video]) as paths:
        video = read_video(args.video, sensor_values(args))
        check_decoder_supports(args.decoder, video.params)
        check_frame_size(files, video.codes.shape)
        if "exr_zip" in files:
            check_video_storable(video.codes, video.params, {"half": args.half})
        progress = None if args.quiet else progress_bar
        start = time.perf_counter()
        decoded = decode_video_frames(video, options, progress)
        targets = {kind: str(paths[file.flag]) for kind, file in files.items()}
        write_outputs(decoded, video, targets, options, progress)
    summary = decoded.summary()
    print(
        f"wrote {', '.join(file.path for file in files.values())}: {summary['frames']} frames, "
        f"mode {args.mode}, decoder {args.decoder}, {summary['ms_per_frame']:.1f} ms/frame "
        f"decoding, {summary['keyframes']} keyframes, {summary['paths']['temporal']:.1%} of "
        f"pixels temporal, {time.perf_counter() - start:.1f} s in all"
    )
    if note := padding_note(files, video.codes.shape[1], video.codes.shape[2]):
        print(note)
    return 0
