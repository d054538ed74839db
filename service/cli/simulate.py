"""``mcam simulate``: expose and encode an HDR scene into a wrapped sensor frame."""

from __future__ import annotations

import argparse
from typing import Any

from models.exr_header import sensor_attributes
from models.formation import SensorParams, simulate
from models.frames import frame_format, write_frame, write_winding
from models.hdr_io import read_hdr, write_exr
from service.cli.options import (
    add_clip_negative_flag,
    add_sensor_flags,
    sensor_values,
)


def register(subparsers: Any) -> None:
    """Add the ``simulate`` command."""
    parser = subparsers.add_parser(
        "simulate",
        help="simulate a wrapping sensor on an HDR scene (OpenEXR or Radiance .hdr)",
        description="Expose an HDR scene and write the wrapped sensor frame it gives "
        "(.png grayscale, .tiff grey or RGB, .npy), parameters stored in the file.",
    )
    parser.add_argument("scene", help="scene-referred HDR image: .exr, .hdr or .pic")
    parser.add_argument("-o", "--output", required=True, help="wrapped frame: .png, .tiff, .npy")
    add_sensor_flags(parser, "defaults: mantissa, alpha 2, 8 bits, gain from --overexposed or 1")
    parser.add_argument(
        "--overexposed",
        type=float,
        help="set the gain so this fraction of pixels (0..1) reaches x >= 1 (instead of --gain)",
    )
    parser.add_argument("--max-wraps", type=float, help="clip x at this many wrap units")
    parser.add_argument("--read-noise", type=float, help="read noise sigma, in wraps (0..1)")
    parser.add_argument("--full-well", type=float, help="electrons at x = 1, for shot noise")
    parser.add_argument("--seed", type=int, help="noise seed")
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


def run(args: argparse.Namespace) -> int:
    """Simulate the frame and write it (plus the optional ground truth and reference)."""
    frame_format(args.output)
    if args.ground_truth:
        frame_format(args.ground_truth)
    scene = read_hdr(args.scene, clip_negative=args.clip_negative)
    noise = {
        "max_wraps": args.max_wraps,
        "read_noise": args.read_noise,
        "full_well": args.full_well,
        "seed": args.seed,
    }
    given = sensor_values(args) | noise
    params = SensorParams.parse({key: value for key, value in given.items() if value is not None})
    frame = simulate(scene.pixels, params, overexposed=args.overexposed, gray=args.gray)
    write_frame(args.output, frame.codes, frame.params)
    if args.ground_truth:
        write_winding(args.ground_truth, frame.winding)
    if args.reference_out:
        attributes = sensor_attributes(frame.params) | {
            "comments": "scene-referred irradiance the simulated sensor saw (x / gain)"
        }
        write_exr(args.reference_out, frame.irradiance / frame.params.gain, attributes)
    shape = " x ".join(str(n) for n in frame.codes.shape)
    print(
        f"wrote {args.output}: {shape} {frame.params.encoding} codes, {frame.params.bits}-bit, "
        f"gain {frame.params.gain:.6g}, W from {frame.winding.min()} to {frame.winding.max()}"
    )
    if scene.negatives_clipped:
        print(f"clipped {scene.negatives_clipped} negative scene values to 0")
    return 0
