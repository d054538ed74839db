"""Shared command-line pieces: the sensor-parameter flags and the EXR attributes they become."""

from __future__ import annotations

import argparse
import logging
import re
from typing import Any

from models.formation import ENCODINGS
from models.hdr_io import DEFAULT_EXR_COMPRESSION, EXR_COMPRESSIONS

#: Levels ``--log-level`` takes (any case).
LOG_LEVELS: tuple[str, ...] = ("DEBUG", "INFO", "WARNING", "ERROR", "CRITICAL")

#: An argument that is an option's value although it starts with ``-``: a ``-`` then a
#: digit (``--stages -1,2,3``, whose own check then says what is wrong). argparse 3.11
#: takes only plain negative numbers, and refused it with "expected one argument".
DASH_DIGIT = re.compile(r"^-\.?\d")

#: Flags that set (simulate) or override (reconstruct) a frame's sensor parameters.
SENSOR_FLAGS: tuple[str, ...] = ("encoding", "alpha", "bits", "gain")


def add_sensor_flags(parser: argparse.ArgumentParser, description: str) -> None:
    """Add ``--encoding --alpha --bits --gain`` (each None unless given) in their own group."""
    group = parser.add_argument_group("sensor parameters", description)
    group.add_argument("--encoding", choices=ENCODINGS, help="how the pixel wraps")
    group.add_argument(
        "--alpha", type=float, help="mantissa base (> 1): one more wrap per factor alpha"
    )
    group.add_argument("--bits", type=int, help="code bit depth, 1..16")
    group.add_argument(
        "--gain", type=float, help="scene irradiance to wrap units: x = gain * scene (> 0)"
    )


def add_log_level_flag(parser: argparse.ArgumentParser) -> None:
    """``--log-level`` of a long-running command (one of :data:`LOG_LEVELS`, any case)."""
    parser.add_argument(
        "--log-level", default="INFO", type=str.upper, choices=LOG_LEVELS,
        help="logging level (default: INFO)",
    )  # fmt: skip


def start_logging(args: argparse.Namespace) -> None:
    """Log at ``args.log_level`` (see :func:`add_log_level_flag`) with times and names."""
    logging.basicConfig(
        level=args.log_level, format="%(asctime)s %(levelname)s %(name)s: %(message)s"
    )


def add_clip_negative_flag(parser: argparse.ArgumentParser) -> None:
    """``--clip-negative``: read HDR images with their negative values set to 0."""
    parser.add_argument(
        "--clip-negative",
        action="store_true",
        help="set negative values of the HDR images read (lossy EXR) to 0 instead of "
        "refusing them",
    )


def add_exr_compression_flag(parser: argparse.ArgumentParser) -> None:
    """``--exr-compression``: how the command's EXR files are compressed (lossless)."""
    parser.add_argument(
        "--exr-compression",
        choices=tuple(EXR_COMPRESSIONS),
        default=DEFAULT_EXR_COMPRESSION,
        help="lossless EXR compression: zip (smaller, default) or none (faster)",
    )


def sensor_values(args: argparse.Namespace) -> dict[str, Any]:
    """The sensor flags as a mapping, None where not given."""
    return {name: getattr(args, name) for name in SENSOR_FLAGS}


def take_dash_digit_values(parser: argparse.ArgumentParser) -> None:
    """Let ``parser`` take an argument starting with ``-`` and a digit as an option's value
    (:data:`DASH_DIGIT`). argparse has no public setting for this; the parser's
    ``_negative_number_matcher`` is the pattern it reads (Python 3.11 to 3.13)."""
    parser._negative_number_matcher = DASH_DIGIT
