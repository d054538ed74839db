"""Control commands as plain mappings (API JSON, Redis stream fields) <-> control packets.

A command is ``{"command": NAME, ...arguments}`` with NAME one of
:data:`COMMANDS`. The API validates a request with :func:`parse_command`, writes
:func:`command_fields` to ``control:<device>``, and the daemon turns each entry
back into a packet with :func:`parse_command` before writing it to the camera.
"""

from __future__ import annotations

from typing import Annotated, Any, Literal

from pydantic import (
    BaseModel,
    BeforeValidator,
    ConfigDict,
    Discriminator,
    Field,
    Tag,
    TypeAdapter,
    ValidationError,
    field_validator,
    model_validator,
)
from pydantic_core import PydanticCustomError

from device.link_protocol import (
    MIN_GAIN,
    REFERENCE_INTEGRATION_NS,
    BracketPacket,
    ControlPacket,
    EncodingPacket,
    ExposurePacket,
    FrameRatePacket,
    StartPacket,
    StopPacket,
)
from models.errors import InvalidInputError, describe_validation_error

_STRICT = ConfigDict(extra="forbid", frozen=True)
#: Frame rates (frames per second) a camera may be set to: from one frame in ten seconds
#: to mcam-link's set_frame_rate limit.
FPS_RANGE = (0.1, 10_000.0)


def _refuse_boolean(value: Any) -> Any:
    """A JSON true/false is not a number (pydantic would read it as 1 or 0)."""
    if isinstance(value, bool):
        raise PydanticCustomError(
            "number_type", "Input should be a number, not {value}", {"value": str(value).lower()}
        )
    return value


#: Number fields of a command: what lax validation takes (strings from stream fields
#: included), except booleans.
Real = Annotated[float, BeforeValidator(_refuse_boolean)]
Whole = Annotated[int, BeforeValidator(_refuse_boolean)]


class StartCommand(BaseModel):
    """Start streaming."""

    model_config = _STRICT
    command: Literal["start"]


class StopCommand(BaseModel):
    """Stop streaming."""

    model_config = _STRICT
    command: Literal["stop"]


class ExposureCommand(BaseModel):
    """Analog gain (wrap units per scene unit at the reference integration) and integration (ns)."""

    model_config = _STRICT
    command: Literal["set_exposure"]
    gain: Real = Field(gt=0, le=1e9, allow_inf_nan=False)
    integration_ns: Whole = Field(REFERENCE_INTEGRATION_NS, gt=0, lt=1 << 63)

    @model_validator(mode="after")
    def _frames_can_carry_the_gain(self) -> ExposureCommand:
        """The gain the camera's frames report (``gain * integration_ns / 1 ms``) must be
        one a data header carries: below it every frame would be dropped as malformed."""
        reported = self.gain * self.integration_ns / REFERENCE_INTEGRATION_NS
        if reported < MIN_GAIN:
            raise PydanticCustomError(
                "gain_range",
                f"gain x integration_ns / {REFERENCE_INTEGRATION_NS} is {reported:g}, below "
                f"the smallest gain a frame can carry ({MIN_GAIN:g}); raise gain or "
                "integration_ns",
            )
        return self


class EncodingCommand(BaseModel):
    """In-pixel encoding, its alpha (mantissa only) and code bits."""

    model_config = _STRICT
    command: Literal["set_encoding"]
    encoding: Literal["modulo", "mantissa", "clip"]
    bits: Whole = Field(8, ge=1, le=16)
    alpha: Real = Field(2.0, gt=1.0, le=1e6, allow_inf_nan=False)


class FrameRateCommand(BaseModel):
    """Frames per second, within :data:`FPS_RANGE`."""

    model_config = _STRICT
    command: Literal["set_frame_rate"]
    fps: Real = Field(ge=FPS_RANGE[0], le=FPS_RANGE[1], allow_inf_nan=False)


class BracketCommand(BaseModel):
    """Bracketed reference capture: ``count`` clipped images, gain times ``ratio`` each."""

    model_config = _STRICT
    command: Literal["bracket"]
    count: Whole = Field(5, ge=2, le=16)
    base_gain: Real = Field(0.0, ge=0, le=1e9, allow_inf_nan=False)
    ratio: Real = Field(2.0, gt=1.0, le=64, allow_inf_nan=False)

    @field_validator("base_gain")
    @classmethod
    def _frames_can_carry_the_base_gain(cls, value: float) -> float:
        """A base gain is 0 (the device's choice) or one a data header carries."""
        if 0 < value < MIN_GAIN:
            raise PydanticCustomError(
                "gain_range",
                f"{value:g} is below the smallest gain a frame can carry ({MIN_GAIN:g}); "
                "give 0 (the device's choice) or a larger gain",
            )
        return value


COMMANDS: tuple[str, ...] = (
    "start", "stop", "set_exposure", "set_encoding", "set_frame_rate", "bracket",
)


def _command_name(value: Any) -> Any:
    """The ``command`` of a mapping or a command model (None when it has none)."""
    return value.get("command") if isinstance(value, dict) else getattr(value, "command", None)


Command = Annotated[
    Annotated[StartCommand, Tag("start")]
    | Annotated[StopCommand, Tag("stop")]
    | Annotated[ExposureCommand, Tag("set_exposure")]
    | Annotated[EncodingCommand, Tag("set_encoding")]
    | Annotated[FrameRateCommand, Tag("set_frame_rate")]
    | Annotated[BracketCommand, Tag("bracket")],
    Discriminator(
        _command_name,
        custom_error_type="unknown_command",
        custom_error_message=(
            f"a command is a JSON object whose field 'command' is one of {', '.join(COMMANDS)}, "
            'e.g. {"command": "start"}'
        ),
    ),
]
_ADAPTER: TypeAdapter[Command] = TypeAdapter(Command)


def validate_command(values: dict[str, Any]) -> Command:
    """Check a command mapping; :class:`InvalidInputError` says which field is wrong."""
    try:
        return _ADAPTER.validate_python(values)
    except ValidationError as exc:
        raise InvalidInputError(
            f"invalid device command: {describe_validation_error(exc, 'command')}"
        ) from None


def to_packet(command: Command) -> ControlPacket:
    """The control packet carrying a validated command."""
    match command:
        case StartCommand():
            return StartPacket()
        case StopCommand():
            return StopPacket()
        case ExposureCommand():
            return ExposurePacket(command.gain, command.integration_ns)
        case EncodingCommand():
            return EncodingPacket(command.encoding, command.bits, command.alpha)
        case FrameRateCommand():
            return FrameRatePacket(command.fps)
        case BracketCommand():
            return BracketPacket(command.count, command.base_gain, command.ratio)
    raise InvalidInputError(f"unknown command {command!r}")


def to_command(packet: ControlPacket) -> Command:
    """The validated command a control packet carries (the device's check of its input)."""
    fields: dict[str, Any] = {
        key: value for key, value in vars(packet).items() if key != "type"
    }
    name = {
        StartPacket: "start", StopPacket: "stop", ExposurePacket: "set_exposure",
        EncodingPacket: "set_encoding", FrameRatePacket: "set_frame_rate",
        BracketPacket: "bracket",
    }[type(packet)]
    return validate_command({"command": name, **fields})


def parse_command(values: dict[str, Any]) -> ControlPacket:
    """Validate a command mapping and return its control packet."""
    return to_packet(validate_command(values))


def command_fields(command: Command) -> dict[str, str]:
    """Redis stream fields of a command (all values as strings)."""
    return {key: str(value) for key, value in command.model_dump().items()}


def _text(value: bytes | str) -> str:
    """A stream field as text, or a clear error when its bytes are not UTF-8."""
    if isinstance(value, str):
        return value
    try:
        return value.decode()
    except UnicodeDecodeError as exc:
        raise InvalidInputError(
            f"a control field is not UTF-8 text ({value[:32]!r}); write commands as text"
        ) from exc


def fields_to_command(fields: dict[bytes | str, bytes | str]) -> Command:
    """Parse the fields of a ``control:<device>`` stream entry."""
    return validate_command({_text(k): _text(v) for k, v in fields.items()})
