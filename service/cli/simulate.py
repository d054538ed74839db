"""``mcam simulate``: expose and encode an HDR scene into a wrapped sensor frame."""

from __future__ import annotations

import argparse
from typing import Any

from models.exposure import check_not_black
from models.exr_header import sensor_attributes
from models.formation import SensorParams, simulate
from models.frames import FRAME_SUFFIXES, frame_format, write_frame
from models.hdr_io import read_hdr, write_exr
from models.winding_files import write_winding
from service.cli.options import (
    add_clip_negative_flag,
    add_sensor_flags,
    sensor_values,
)
from service.cli.output_files import OutputFile, staged_outputs


def register(subparsers: Any) -> None:
    """Add the ``simulate`` command."""
    parser = subparsers.add_parser(
        "simulate",
        help="simulate a wrapping sensor on an HDR scene (OpenEXR or Radiance .hdr)",
        description="Expose an HDR scene and write the wrapped sensor frame it gives: "
        ".png (grayscale) or .tiff (grey or RGB) store the parameters in the file; .npy "
        "stores the codes only (the command prints the flags mcam reconstruct needs).",
    )
    parser.add_argument("scene", help="scene-referred HDR image: .exr, .hdr or .pic")
    parser.add_argument(
        "-o", "--output", required=True, help="wrapped frame: .png, .tiff, .npy (codes only)"
    )
    add_sensor_flags(parser, "defaults: mantissa, alpha 2, 8 bits, gain from --overexposed or 1")
    parser.add_argument(
        "--overexposed",
        type=float,
        help="set the gain so this fraction of pixels (strictly between 0 and 1) reaches "
        "x >= 1 (instead of --gain)",
    )
    parser.add_argument(
        "--max-wraps", type=float, help="clip x at this many wrap units (at least 1)"
    )
    parser.add_argument("--read-noise", type=float, help="read noise sigma, in wraps (0..1)")
    parser.add_argument(
        "--full-well", type=float, help="electrons at x = 1, for shot noise (at least 1)"
    )
    parser.add_argument(
        "--seed",
        type=int,
        default=0,
        help="noise seed (default 0): the same seed draws the same noise; .png and .tiff "
        "frames store it",
    )
    parser.add_argument("--gray", action="store_true", help="encode Rec.709 luminance of RGB")
    add_clip_negative_flag(parser)
    parser.add_argument("--ground-truth", metavar="W.png", help="also write the true W map")
    parser.add_argument(
        "--reference-out",
        metavar="REF.exr",
        help="also write the irradiance the sensor saw (after --max-wraps), scene-referred, "
        "as the reference for mcam evaluate",
    )
    parser.set_defaults(func=run)


def outputs(args: argparse.Namespace) -> list[OutputFile]:
    """The files the command writes: the frame and the optional W map and reference."""
    files = [OutputFile("-o", args.output, "a wrapped frame is PNG, TIFF or .npy", FRAME_SUFFIXES)]
    if args.ground_truth:
        files.append(
            OutputFile(
                "--ground-truth", args.ground_truth, "a W map is PNG, TIFF or .npy", FRAME_SUFFIXES
            )
        )
    if args.reference_out:
        files.append(
            OutputFile("--reference-out", args.reference_out, "the reference is OpenEXR", (".exr",))
        )
    return files


def reconstruct_flags(params: SensorParams) -> str:
    """The ``mcam reconstruct`` flags that restore parameters a ``.npy`` does not store."""
    flags = f"--encoding {params.encoding} --alpha {params.alpha!r} --bits {params.bits}"
    return f"{flags} --gain {params.gain!r}" if params.gain is not None else flags


def run(args: argparse.Namespace) -> int:
    """Simulate the frame and write it (plus the optional ground truth and reference)."""
    with staged_outputs(outputs(args), [args.scene]) as paths:
        scene = read_hdr(args.scene, clip_negative=args.clip_negative)
        noise = {
            "max_wraps": args.max_wraps,
            "read_noise": args.read_noise,
            "full_well": args.full_well,
            "seed": args.seed,
        }
        given = sensor_values(args) | noise
        params = SensorParams.parse({k: v for k, v in given.items() if v is not None})
        frame = simulate(scene.pixels, params, overexposed=args.overexposed, gray=args.gray)
        check_not_black(frame)
        write_frame(paths["-o"], frame.codes, frame.params)
        if args.ground_truth:
            write_winding(paths["--ground-truth"], frame.winding)
        if args.reference_out:
            attributes = sensor_attributes(frame.params) | {
                "comments": "scene-referred irradiance the simulated sensor saw (x / gain)"
            }
            gain = frame.params.gain
            write_exr(
                paths["--reference-out"], frame.irradiance / gain, attributes, scene_gain=gain
            )
    shape = " x ".join(str(n) for n in frame.codes.shape)
    print(
        f"wrote {args.output}: {shape} {frame.params.encoding} codes, {frame.params.bits}-bit, "
        f"gain {frame.params.gain:.6g}, W from {frame.winding.min()} to {frame.winding.max()}"
    )
    if frame_format(args.output) == "npy":
        print(
            f"{args.output} holds the codes only: reconstruct it with "
            f"{reconstruct_flags(frame.params)}"
        )
    if scene.negatives_clipped:
        print(f"clipped {scene.negatives_clipped} negative scene values to 0")
    return 0
