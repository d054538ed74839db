"""Tests of device/commands.py: control commands as mappings, stream fields and packets."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from device import link_protocol as lp
from device.commands import (
    COMMANDS,
    FPS_RANGE,
    command_fields,
    fields_to_command,
    parse_command,
    to_command,
    validate_command,
)
from models.errors import InvalidInputError

EXAMPLES: dict[str, dict[str, Any]] = {
    "start": {"command": "start"},
    "stop": {"command": "stop"},
    "set_exposure": {"command": "set_exposure", "gain": 2.5, "integration_ns": 500_000},
    "set_encoding": {"command": "set_encoding", "encoding": "mantissa", "bits": 10, "alpha": 3.0},
    "set_frame_rate": {"command": "set_frame_rate", "fps": 120.0},
    "bracket": {"command": "bracket", "count": 4, "base_gain": 0.5, "ratio": 4.0},
}


def test_every_command_has_an_example() -> None:
    assert set(EXAMPLES) == set(COMMANDS)


@pytest.mark.parametrize("name", COMMANDS)
def test_a_command_survives_the_stream_and_the_link(name: str) -> None:
    """API mapping -> Redis fields (strings) -> command -> packet -> command: unchanged."""
    command = validate_command(EXAMPLES[name])
    assert command.model_dump() == {**command.model_dump(), **EXAMPLES[name]}
    assert fields_to_command(command_fields(command)) == command
    encoded = {k.encode(): v.encode() for k, v in command_fields(command).items()}
    assert fields_to_command(encoded) == command
    assert to_command(parse_command(EXAMPLES[name])) == command


@pytest.mark.parametrize("values", [{}, {"command": "fly"}, {"fps": 30}, {"command": None}])
def test_a_missing_or_unknown_command_names_the_commands(values: dict[str, Any]) -> None:
    with pytest.raises(InvalidInputError, match="field 'command' is one of start, stop,"):
        validate_command(values)


@pytest.mark.parametrize(
    ("values", "field"),
    [
        ({"command": "set_frame_rate", "fps": -1}, "set_frame_rate.fps"),
        ({"command": "set_frame_rate", "fps": 1e-300}, "set_frame_rate.fps"),
        ({"command": "set_frame_rate", "fps": 0.099}, "set_frame_rate.fps"),
        ({"command": "set_frame_rate", "fps": 10_000.5}, "set_frame_rate.fps"),
        ({"command": "set_exposure", "gain": float("nan")}, "set_exposure.gain"),
        ({"command": "set_encoding", "encoding": "gamma"}, "set_encoding.encoding"),
        ({"command": "bracket", "count": 1}, "bracket.count"),
        ({"command": "start", "speed": 2}, "start.speed"),
    ],
)
def test_a_bad_argument_is_named(values: dict[str, Any], field: str) -> None:
    with pytest.raises(InvalidInputError, match=f"^invalid device command: {field}: "):
        validate_command(values)


def test_the_frame_rate_range_is_the_cameras() -> None:
    for fps in FPS_RANGE:
        assert validate_command({"command": "set_frame_rate", "fps": fps}).fps == fps


@pytest.mark.parametrize(
    "values",
    [
        {"command": "set_frame_rate", "fps": True},
        {"command": "set_exposure", "gain": True},
        {"command": "set_exposure", "gain": 1.0, "integration_ns": True},
        {"command": "set_encoding", "encoding": "clip", "bits": True},
        {"command": "set_encoding", "encoding": "mantissa", "alpha": False},
        {"command": "bracket", "count": True},
        {"command": "bracket", "ratio": True},
        {"command": "bracket", "base_gain": False},
    ],
)
def test_a_json_boolean_is_not_a_number(values: dict[str, Any]) -> None:
    name = next(key for key, value in values.items() if isinstance(value, bool))
    with pytest.raises(InvalidInputError, match=f"{values['command']}.{name}: .*not (true|false)"):
        validate_command(values)


@pytest.mark.parametrize(
    ("values", "field"),
    [
        ({"command": "set_exposure", "gain": 5e-324}, "set_exposure"),
        ({"command": "set_exposure", "gain": 1e-305, "integration_ns": 1}, "set_exposure"),
        ({"command": "bracket", "base_gain": 1e-320}, "bracket.base_gain"),
    ],
)
def test_a_gain_no_frame_can_carry_is_refused(values: dict[str, Any], field: str) -> None:
    """A frame's gain is a normal f64 or 0 (mcam-link v1): a camera set below that sent
    frames the daemon dropped, every one, as malformed."""
    with pytest.raises(InvalidInputError,
                       match=f"^invalid device command: {field}: .*smallest gain a frame can"):
        validate_command(values)


def test_the_smallest_exposure_accepted_gives_frames_the_link_carries() -> None:
    smallest = validate_command({"command": "set_exposure", "gain": lp.MIN_GAIN})
    reported = smallest.gain * smallest.integration_ns / lp.REFERENCE_INTEGRATION_NS
    wire = lp.encode_data(lp.DataPacket(0, 0, "modulo", 2.0, 8, reported,
                                        np.zeros((2, 2), np.uint8)))
    assert lp.decode_data(wire[lp.HEADER_SIZE:-lp.CRC_SIZE]).gain == reported
