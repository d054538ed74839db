"""Decoder lookup by name: one cached instance per decoder (ONNX sessions are created once).

Each decoder module exposes ``specs() -> list[DecoderSpec]``; the registry
collects them from :data:`PROVIDERS` in order. A provider whose optional
files are missing (e.g. no ONNX models) simply offers no specs.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable
from dataclasses import dataclass, field
from functools import cache
from typing import Any

from models.decoders.base import Decoder
from models.errors import InvalidInputError

#: Modules that offer decoders, each with a ``specs()`` function.
PROVIDERS: tuple[str, ...] = (
    "models.decoders.classical",
    "models.decoders.graphcut",
    "models.decoders.learned",
    "models.decoders.adaptive",
)


@dataclass(frozen=True)
class DecoderSpec:
    """A selectable decoder: its name, family, a one-line description, a factory, and
    measured figures (from a model card or the benchmark) to help users choose."""

    name: str
    kind: str
    description: str
    factory: Callable[[], Decoder] = field(repr=False, compare=False)
    figures: dict[str, Any] = field(default_factory=dict, compare=False)


@cache
def _specs() -> dict[str, DecoderSpec]:
    found: dict[str, DecoderSpec] = {}
    for module_name in PROVIDERS:
        try:
            module = importlib.import_module(module_name)
        except ModuleNotFoundError as exc:
            if exc.name != module_name:
                raise
            continue
        for spec in module.specs():
            found[spec.name] = spec
    return found


def available_decoders() -> list[DecoderSpec]:
    """All decoders this installation can run, in registration order."""
    return list(_specs().values())


@cache
def get_decoder(name: str) -> Decoder:
    """The shared instance of decoder ``name``; a clear error lists the valid names."""
    specs = _specs()
    if name not in specs:
        raise InvalidInputError(
            f"unknown decoder {name!r}; choose one of: {', '.join(specs) or '(none installed)'}"
        )
    return specs[name].factory()
