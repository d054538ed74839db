"""A frame's sensor parameters: those it stores merged with the caller's.

The stored parameters (parsed by :mod:`models.stored_params`) are merged with
overrides (command-line flags or form fields, which win) and validated; what is
missing or wrong is named with the flags and form fields that give it.
"""

from __future__ import annotations

import logging
from typing import Any

from pydantic import ValidationError

from models.errors import InvalidInputError, MissingParameterError
from models.formation import SensorParams
from models.stored_params import StoredParams, UnreadableParams

#: Parameters a frame cannot be decoded without, with an example value of each.
_REQUIRED = {"encoding": "mantissa", "bits": "8"}
logger = logging.getLogger(__name__)


def _missing(values: dict[str, Any]) -> dict[str, str]:
    """The parameters a frame cannot be decoded without that ``values`` lack, each with
    an example value."""
    needed = dict(_REQUIRED)
    if values.get("encoding") == "mantissa":
        needed["alpha"] = "2"
    return {key: example for key, example in needed.items() if key not in values}


def _asking_for(missing: dict[str, str]) -> str:
    """How to give ``missing`` parameters, as flags and as form fields (and, when the
    encoding is missing, that a mantissa frame needs its alpha too: asked for only after
    the encoding came, it took a second refusal)."""
    flags = " ".join(f"--{key.replace('_', '-')} {example}" for key, example in missing.items())
    fields = ", ".join(f"{key}={example}" for key, example in missing.items())
    mantissa = (
        "; a mantissa frame also needs its alpha (--alpha 2, alpha=2)"
        if "encoding" in missing else ""
    )
    return f"command line: {flags}; HTTP: the form fields {fields}{mantissa}"


def _asked(missing: dict[str, str]) -> list[str]:
    """The parameters that :func:`_asking_for` asks for: ``missing``, and alpha when the
    encoding is missing."""
    return [*missing, *(["alpha"] if "encoding" in missing else [])]


def merge_params(stored: StoredParams, overrides: dict[str, Any] | None) -> SensorParams:
    """Stored parameters updated by ``overrides`` (None values ignored), checked complete.

    Raises :class:`MissingParameterError` naming the parameters to give (as
    command-line flags and as HTTP form fields) when the encoding, the bit depth or
    (for mantissa) alpha is known from neither. Unreadable stored parameters are
    ignored, with a warning logged, when ``overrides`` hold all it needs; else refused.
    """
    given = {key: value for key, value in (overrides or {}).items() if value is not None}
    if isinstance(stored, UnreadableParams):
        if missing := _missing(given):
            raise InvalidInputError(
                f"{stored.problem}; give the parameters to decode the frame without it "
                f"({_asking_for(missing)})",
                _asked(missing),
            )
        logger.warning("%s; ignored it: decoding with the parameters given", stored.problem)
        stored = {}
    merged = {key: value for key, value in stored.items() if value is not None} | given
    missing = _missing(merged)
    if missing:
        raise MissingParameterError(
            f"the frame does not store its {', '.join(missing)}; give them as parameters "
            f"({_asking_for(missing)})",
            _asked(missing),
        )
    try:
        return SensorParams.parse(merged)
    except InvalidInputError as exc:
        if stored_faults := _stored_faults(merged, given):
            overrides = {key: "<value>" for key in stored_faults}
            raise InvalidInputError(
                f"{exc.message}; the frame stores {', '.join(stored_faults)}: give the right "
                f"value as a parameter to override it ({_asking_for(overrides)})",
                stored_faults,
            ) from None
        raise


def _stored_faults(merged: dict[str, Any], given: dict[str, Any]) -> list[str]:
    """The parameters of ``merged`` that are out of range and come from the frame's
    stored text, not from ``given`` (the caller's)."""
    try:
        SensorParams.model_validate(merged)
    except ValidationError as exc:
        fields = {str(error["loc"][0]) for error in exc.errors() if error["loc"]}
        return sorted(fields - set(given))
    return []
