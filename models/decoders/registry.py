"""Decoder lookup by name: one cached instance per decoder (ONNX sessions are created once).

Each decoder module exposes ``specs() -> list[DecoderSpec]``; the registry
collects them from :data:`PROVIDERS` in order. A provider whose optional
files are missing (e.g. no ONNX models) simply offers no specs. A provider may
also resolve parametrized names (``resolve(name) -> DecoderSpec | None``, e.g.
``auto-40ms``) and describe them in ``NAME_PATTERNS``.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable
from dataclasses import dataclass, field
from functools import cache
from types import ModuleType
from typing import Any

from models.decoders.base import Decoder
from models.errors import InvalidInputError

#: Modules that offer decoders, each with a ``specs()`` function.
PROVIDERS: tuple[str, ...] = (
    "models.decoders.classical",
    "models.decoders.graphcut",
    "models.decoders.learned",
    "models.decoders.guided_puma",
    "models.decoders.adaptive",
    "models.decoders.budget",
    "models.decoders.colour",
)


@dataclass(frozen=True)
class DecoderSpec:
    """A selectable decoder: its name, family, a one-line description, a factory, and
    the figures its model cards state, with where they come from (``figures_source``);
    :func:`models.decoders.measured.measured_figures` adds the benchmark's for the others."""

    name: str
    kind: str
    description: str
    factory: Callable[[], Decoder] = field(repr=False, compare=False)
    figures: dict[str, Any] = field(default_factory=dict, compare=False)
    figures_source: str = field(default="", compare=False)
    budgeted: bool = field(default=False, compare=False)


def refuse_budget_inside(wrapper: str, inner: DecoderSpec, why: str) -> None:
    """Refuse a latency-budgeted decoder (``auto-<N>ms``) inside ``wrapper`` (a name such
    as ``+colour``): its budget bounds one frame, and the wrapper ``why``."""
    if inner.budgeted:
        raise InvalidInputError(
            f"{inner.name}{wrapper}: a latency budget bounds the whole frame, but {why}; "
            f"use {inner.name} alone, or a quality (auto-fast, auto-balanced, auto-best) "
            f"with {wrapper}"
        )


@cache
def _providers() -> tuple[ModuleType, ...]:
    found = []
    for module_name in PROVIDERS:
        try:
            found.append(importlib.import_module(module_name))
        except ModuleNotFoundError as exc:
            if exc.name != module_name:
                raise
    return tuple(found)


@cache
def _specs() -> dict[str, DecoderSpec]:
    return {spec.name: spec for module in _providers() for spec in module.specs()}


def available_decoders() -> list[DecoderSpec]:
    """All decoders this installation can run, in registration order."""
    return list(_specs().values())


def name_patterns() -> list[str]:
    """Descriptions of the parametrized decoder names the providers resolve."""
    return [text for module in _providers() for text in getattr(module, "NAME_PATTERNS", ())]


def resolve(name: str) -> DecoderSpec:
    """The spec of decoder ``name`` (listed, or parametrized); a clear error lists the
    valid names."""
    specs = _specs()
    if name in specs:
        return specs[name]
    for module in _providers():
        resolver = getattr(module, "resolve", None)
        if resolver is not None and (spec := resolver(name)) is not None:
            return spec
    choices = ", ".join([*specs, *name_patterns()]) or "(none installed)"
    raise InvalidInputError(f"unknown decoder {name!r}; choose one of: {choices}")


@cache
def get_decoder(name: str) -> Decoder:
    """The shared instance of decoder ``name``; a clear error lists the valid names."""
    return resolve(name).factory()
