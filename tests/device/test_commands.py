"""Tests of device/commands.py: control commands as mappings, stream fields and packets."""

from __future__ import annotations

from typing import Any

import pytest

from device.commands import (
    COMMANDS,
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
        ({"command": "set_exposure", "gain": float("nan")}, "set_exposure.gain"),
        ({"command": "set_encoding", "encoding": "gamma"}, "set_encoding.encoding"),
        ({"command": "bracket", "count": 1}, "bracket.count"),
        ({"command": "start", "speed": 2}, "start.speed"),
    ],
)
def test_a_bad_argument_is_named(values: dict[str, Any], field: str) -> None:
    with pytest.raises(InvalidInputError, match=f"^invalid device command: {field}: "):
        validate_command(values)
