"""Errors raised for bad input or impossible requests.

Every error carries a stable machine-readable ``code`` (used by the REST API and
the CLI) and a human message that says what was wrong and what to do about it.
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from contextlib import contextmanager

from pydantic import ValidationError


class McamError(ValueError):
    """Base class: a caller's mistake or an impossible request, never a bug."""

    code = "invalid_input"
    http_status = 422
    #: Seconds a client should wait before retrying (the API's ``Retry-After``); None
    #: for a mistake that retrying does not mend.
    retry_after_s: int | None = None

    def __init__(self, message: str, parameters: Sequence[str] = ()) -> None:
        """``parameters``: the parameters (their form field names) the message asks the
        caller to give, for a client to point at its own fields (the API's
        ``parameters``); empty when it asks for none."""
        super().__init__(message)
        self.message = message
        self.parameters = tuple(parameters)


class InvalidInputError(McamError):
    """Input data is malformed: wrong dtype, NaN/inf, negative irradiance, codes out of range."""

    code = "invalid_input"


class NegativeIrradianceError(InvalidInputError):
    """A scene holds negative values (lossy EXR compression leaves some) and the caller
    did not ask for them to be set to 0 (``clip_negative``)."""

    code = "negative_irradiance"


class MissingParameterError(McamError):
    """A wrapped frame lacks encoding parameters and none were given on the command line or form."""

    code = "missing_parameter"


class UnsupportedFormatError(McamError):
    """A file is not in a format we read or write."""

    code = "unsupported_format"
    http_status = 415


class FormatCannotHoldError(McamError):
    """An output format asked for cannot hold this result (a colour frame as PNG, W
    over 65535 as a 16-bit PNG or TIFF): the request is well-formed, and another format
    holds the result. Not :class:`UnsupportedFormatError`, whose 415 is about the
    format of what the caller sent."""

    code = "format_cannot_hold_result"


class OutputOverflowError(McamError):
    """The reconstruction does not fit the requested output dtype (float32 or float16)."""

    code = "output_overflow"


class OutputUnderflowError(McamError):
    """Nonzero values of the reconstruction would round to zero in the output dtype."""

    code = "output_underflow"


class ImageTooLargeError(McamError):
    """An image exceeds the configured pixel or byte limit."""

    code = "image_too_large"
    http_status = 413


#: Characters of a caller's text an error message quotes; past them it says how long
#: the text was (a 100 KB decoder name came back whole, in a 101 KB error body).
ECHO_CHARS = 80


def echo(text: str, limit: int = ECHO_CHARS) -> str:
    """``text`` quoted for an error message (``repr``): whole up to ``limit`` characters,
    else its first ``limit`` and the count of the rest."""
    if len(text) <= limit:
        return repr(text)
    return f"{text[:limit]!r}... (and {len(text) - limit} more characters)"


def describe_validation_error(exc: ValidationError, subject: str) -> str:
    """One line naming each invalid field of a pydantic error (``field: problem; ...``)."""
    return "; ".join(
        f"{'.'.join(str(p) for p in err['loc']) or subject}: {err['msg']}" for err in exc.errors()
    )


@contextmanager
def naming(label: str) -> Iterator[None]:
    """Prefix ``label`` (a file's path, a video frame's index) to the message of a
    :class:`McamError` raised inside, so that a command reading several files (a job
    decoding many frames) says which one was bad."""
    try:
        yield
    except McamError as exc:
        raise type(exc)(f"{label}: {exc.message}") from None
