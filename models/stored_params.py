"""Sensor parameters stored with a wrapped frame (a PNG text chunk, a TIFF
ImageDescription), parsed strictly: a JSON object of :class:`SensorParams` field names,
every parameter other than the encoding a JSON number (or null), text over
:data:`MAX_PARAMS_TEXT` characters not parsed. Text that cannot be used is
:class:`UnreadableParams`, saying why; :func:`models.frame_params.merge_params` decides whether
the frame can do without it.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from typing import Any

from models.formation import SensorParams

#: The longest stored parameter text that is parsed, in characters: ours (the sensor
#: parameters as JSON) is under 250. A 60 MB TIFF ImageDescription of ``[[],[],...]``
#: took ``json.loads`` 5-7 s and 1.2 GB, stalling the API.
MAX_PARAMS_TEXT = 64 * 1024


@dataclass(frozen=True)
class UnreadableParams:
    """Stored parameter text that cannot be used (damaged, or written by other software):
    ``problem`` says why. :func:`models.frame_params.merge_params` ignores it when the caller
    gives every parameter the frame needs, and refuses the frame otherwise."""

    problem: str


StoredParams = dict[str, Any] | UnreadableParams


def _parameter_object(text: str | None, where: str) -> StoredParams:
    """The JSON object of sensor parameter names that stored ``text`` holds; {} when
    there is none. Text longer than :data:`MAX_PARAMS_TEXT` is not parsed."""
    if not text:
        return {}
    if len(text) > MAX_PARAMS_TEXT:
        return UnreadableParams(
            f"the {where} holds {len(text)} characters, more than sensor parameters take "
            f"(at most {MAX_PARAMS_TEXT} are read)"
        )
    try:
        values = json.loads(text)
    except (ValueError, RecursionError):  # JSONDecodeError, an int of over 4300 digits
        return UnreadableParams(f"the {where} is not valid JSON sensor parameters")
    if not isinstance(values, dict):
        return UnreadableParams(f"the {where} holds JSON but not an object of sensor parameters")
    unknown = sorted(set(values) - set(SensorParams.model_fields))
    if unknown:
        return UnreadableParams(f"the {where} holds unknown parameter names {unknown}")
    return values


def _numbers_checked(values: dict[str, Any], where: str) -> StoredParams:
    """``values``, or :class:`UnreadableParams` naming the first parameter other than
    the encoding stored as anything but a JSON number (or null): validated as given,
    ``"bits": true`` became 1 bit (then "not 1-bit"), ``"gain": true`` a gain of 1."""
    for name, value in values.items():
        number = isinstance(value, int | float) and not isinstance(value, bool)
        if name != "encoding" and value is not None and not number:
            shown = json.dumps(value)
            shown = shown if len(shown) <= 40 else shown[:37] + "..."
            return UnreadableParams(f"the {where} stores {name} as {shown}, not a number")
    return values


def parse_stored_params(text: str | None, where: str) -> StoredParams:
    """Parameters parsed from stored JSON text (:func:`_parameter_object`), their
    numbers checked (:func:`_numbers_checked`); {} when there is none."""
    values = _parameter_object(text, where)
    return values if isinstance(values, UnreadableParams) else _numbers_checked(values, where)


def tiff_params(description: str | None) -> StoredParams:
    """Our sensor parameters from a TIFF ImageDescription; {} when it holds none, or
    holds text that other software wrote there (any text that is not a JSON object of
    sensor parameter names, or longer than :data:`MAX_PARAMS_TEXT`: OME-XML runs to
    megabytes): those frames take their parameters from the caller. Ours with a
    parameter that is not a number are :class:`UnreadableParams`."""
    where = "TIFF ImageDescription"
    values = _parameter_object(description, where)
    return {} if isinstance(values, UnreadableParams) else _numbers_checked(values, where)
