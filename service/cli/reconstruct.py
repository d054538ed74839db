"""``mcam reconstruct``: decode a wrapped frame into an OpenEXR HDR image."""

from __future__ import annotations

import argparse
import sys
from typing import Any

import numpy as np

from models.decodable import check_decodable
from models.decoders import available_decoders, get_decoder
from models.decoders.registry import name_patterns
from models.errors import FormatCannotHoldError, MissingParameterError
from models.exr_header import reconstruction_attributes, values_unit
from models.formation import reconstruct
from models.frames import FRAME_SUFFIXES, frame_format, read_frame
from models.hdr_io import write_exr
from models.winding_files import write_winding
from service.cli.options import (
    add_exr_compression_flag,
    add_sensor_flags,
    sensor_values,
)
from service.cli.output_files import OutputFile, staged_outputs


def register(subparsers: Any) -> None:
    """Add the ``reconstruct`` command."""
    parser = subparsers.add_parser(
        "reconstruct",
        help="recover the HDR image of a wrapped frame (writes OpenEXR)",
        description="Decode a wrapped frame (.png, .tiff, .npy) into an OpenEXR image: "
        "scene-referred values (x / gain) when the gain is known, else wrap units x.",
    )
    parser.add_argument("frame", nargs="?", help="wrapped frame: .png, .tiff or .npy")
    parser.add_argument("-o", "--output", metavar="HDR.exr", help="OpenEXR file to write")
    parser.add_argument("--decoder", default="itoh", help="decoder name (default: itoh)")
    parser.add_argument(
        "--list-decoders", action="store_true", help="list the installed decoders and exit"
    )
    add_sensor_flags(parser, "fill in or override the parameters stored in the frame")
    parser.add_argument("--half", action="store_true", help="write half floats (float16)")
    add_exr_compression_flag(parser)
    parser.add_argument("--winding-out", metavar="W.png", help="also write the decoded W map")
    parser.set_defaults(func=run)


def list_decoders() -> int:
    """Print each installed decoder's name, family and description."""
    specs = available_decoders()
    width = max((len(spec.name) for spec in specs), default=0)
    for spec in specs:
        print(f"{spec.name:<{width}}  {spec.kind:<10}  {spec.description}")
    for pattern in name_patterns():
        print(f"also: {pattern}")
    return 0


def outputs(args: argparse.Namespace) -> list[OutputFile]:
    """The files the command writes: the EXR and the optional W map."""
    files = [OutputFile("-o", args.output, "a reconstruction is written as OpenEXR", (".exr",))]
    if args.winding_out:
        files.append(
            OutputFile(
                "--winding-out", args.winding_out, "a W map is PNG, TIFF or .npy", FRAME_SUFFIXES
            )
        )
    return files


def run(args: argparse.Namespace) -> int:
    """Decode the frame and write the EXR (and the optional W map)."""
    if args.list_decoders:
        return list_decoders()
    if args.frame is None or args.output is None:
        raise MissingParameterError(
            "give a wrapped frame and -o OUTPUT.exr (or --list-decoders to see the decoders)"
        )
    with staged_outputs(outputs(args), [args.frame]) as paths:
        decoder = get_decoder(args.decoder)
        frame = read_frame(args.frame, sensor_values(args))
        if args.winding_out and is_colour(frame.codes) and frame_format(args.winding_out) == "png":
            raise FormatCannotHoldError(  # before the decode, not after it
                f"{args.frame} is a colour frame: its W map has {frame.codes.shape[2]} "
                "channels, which a PNG W map (one channel) cannot hold; give --winding-out "
                "a .tiff or .npy name, which hold colour W maps"
            )
        dtype = np.float16 if args.half else np.float32
        check_decodable(frame.codes, frame.params, dtype, scene_referred=True)
        result = decoder.decode(frame.codes, frame.params)
        pixels = reconstruct(frame.codes, result.winding, frame.params, dtype, scene_referred=True)
        attributes = reconstruction_attributes(frame.params, result.info, args.frame)
        write_exr(
            paths["-o"], pixels, attributes, half=args.half, compression=args.exr_compression
        )
        if args.winding_out:
            write_winding(paths["--winding-out"], result.winding)
    print(
        f"wrote {args.output}: decoder {decoder.name}, W from {result.winding.min()} to "
        f"{result.winding.max()}, {result.timings_ns['total'] / 1e6:.1f} ms, values in "
        f"{values_unit(frame.params)}"
    )
    for label, text in decoder_notes(result.info):
        print(f"mcam reconstruct: {label}: {text}", file=sys.stderr)
    channels = result.info.get("channels", [result.info.get("details") or {}])
    for facts in filter(None, (channel.get("budget") for channel in channels)):
        print(budget_summary(facts))
    if (frame := result.info.get("budget")) is not None:
        joined = "made consistent" if frame["joined"] else "not joined (no time for it)"
        print(
            f"latency budget {frame['budget_ms']:g} ms for the colour frame, shared by its "
            f"channels ({joined}): {frame['measured_ms']:.1f} ms in all, "
            f"{'within' if frame['met'] else 'over'} budget{calibration_note(frame)}"
        )
    return 0


def is_colour(codes: np.ndarray) -> bool:
    """Whether a frame's codes (H x W or H x W x C) hold more than one channel."""
    return codes.ndim == 3 and codes.shape[2] > 1


def decoder_notes(facts: Any) -> list[tuple[str, str]]:
    """What a decode's ``info`` (``DecodeResult.info``) tells its reader, each once, in
    order: a net that handed the frame to another decoder (``fallback``: a ``note`` with
    its reason) or whose W falls short of part of it (``warning``), wherever it sits (a
    channel's facts, the guide of ``+puma``, ``auto``'s hard tiles)."""
    notes: list[tuple[str, str]] = []
    if isinstance(facts, dict):
        for key, value in facts.items():
            if key == "fallback" and isinstance(value, dict) and "reason" in value:
                notes.append(("note", str(value["reason"])))
            elif key == "warning" and isinstance(value, str):
                notes.append(("warning", value))
            else:
                notes.extend(decoder_notes(value))
    elif isinstance(facts, list):
        for value in facts:
            notes.extend(decoder_notes(value))
    return list(dict.fromkeys(notes))


def budget_summary(facts: dict[str, Any]) -> str:
    """One line on a latency budget's choice (``info["budget"]`` of ``auto-<N>ms``)."""
    chosen = facts["chosen"]
    line = (
        f"latency budget {facts['budget_ms']:g} ms: {chosen} (predicted "
        f"{facts['predicted_ms'][chosen]:.1f} ms) took {facts['measured_ms']:.1f} ms, "
        f"{'within' if facts['met'] else 'over'} budget"
    )
    return line + calibration_note(facts)


def calibration_note(facts: dict[str, Any]) -> str:
    """What a latency budget's first decode in this process spent measuring the machine's
    costs (``calibration_ms``, outside the budget's figures), when it took 1 ms or more;
    "" otherwise."""
    if facts.get("calibration_ms", 0.0) < 1.0:
        return ""
    return (
        f"; measuring this machine's costs first took {facts['calibration_ms']:.0f} ms "
        "(once per process)"
    )
