"""Decoder lookup by name: one shared instance per decoder (ONNX sessions are created once;
of the parametrized names, the :data:`PARAMETRIZED_KEPT` most recently used are kept).

Each decoder module exposes ``specs() -> list[DecoderSpec]``; the registry
collects them from :data:`PROVIDERS` in order. A provider whose optional
files are missing (e.g. no ONNX models) simply offers no specs. A provider may
also resolve parametrized names (``resolve(name) -> DecoderSpec | None``, e.g.
``auto-40ms``) and describe them in ``NAME_PATTERNS``. One that wraps any decoder in a
suffix (``+puma``, ``+colour``) gives its ``SUFFIX`` and a ``SUFFIX_PATTERN`` (a regex):
a name takes each suffix at most once, in the order of :data:`PROVIDERS`
(``herraez+puma+colour``), and other compositions are refused by name.
"""

from __future__ import annotations

import importlib
import itertools
import re
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field
from functools import cache, lru_cache
from types import ModuleType
from typing import Any
from urllib.parse import quote

from models.decoders.base import Decoder
from models.errors import InvalidInputError, echo
from models.formation import SensorParams

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
#: Parametrized decoders (``auto-<N>ms``, ``<decoder>+puma<K>``, ``<decoder>+colour``)
#: kept built at once, the least recently used dropped first: a request may name any of
#: unboundedly many (``latency_ms`` is any number), and a long-running worker kept every
#: one it had been asked for. Their expensive parts (a network's ONNX session, the cost
#: calibration) belong to listed decoders and to :mod:`models.decoders.cost_model`,
#: which stay built, so one rebuilt after it was dropped costs microseconds.
PARAMETRIZED_KEPT = 64


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


@cache
def _suffixes() -> tuple[tuple[str, re.Pattern[str]], ...]:
    """Each wrapping suffix and its pattern, in the order they compose."""
    return tuple(
        (module.SUFFIX, re.compile(module.SUFFIX_PATTERN))
        for module in _providers()
        if hasattr(module, "SUFFIX_PATTERN")
    )


def _composition_problem(found: list[tuple[int, str]]) -> str | None:
    """What is wrong with suffixes ``found`` ((rank, label) in the name's order): a
    repeat or one out of order; None when they compose."""
    ranks = [rank for rank, _ in found]
    counts = Counter(ranks)
    repeated = sorted({label for rank, label in found if counts[rank] > 1})
    if repeated:
        return f"repeats {' and '.join(repeated)}"
    late = next((i for i in range(1, len(ranks)) if ranks[i] < ranks[i - 1]), None)
    if late is not None:
        return f"puts {found[late - 1][1]} before {found[late][1]}"
    return None


def check_composition(name: str) -> None:
    """Refuse a name whose suffixes repeat or come out of order (``graphcut+puma+colour+
    puma``), naming the valid forms and, as a suggestion, the name composed in order."""
    base, *parts = name.split("+")
    suffixes = _suffixes()
    found = [  # (rank, part) of each part that is a suffix, in the name's order
        (rank, part) for part in parts for rank, (_, pattern) in enumerate(suffixes)
        if pattern.fullmatch(f"+{part}")
    ]  # fmt: skip
    problem = _composition_problem([(rank, suffixes[rank][0]) for rank, _ in found])
    if problem is None:
        return
    labels = [label for label, _ in suffixes]
    masks = sorted(itertools.product((False, True), repeat=len(labels)), key=sum)
    forms = ", ".join(
        "<decoder>" + "".join(label for label, used in zip(labels, mask, strict=True) if used)
        for mask in masks
    )
    first = dict(reversed(found))  # each suffix as first written
    written = {part for _, part in found}
    plain = "".join(f"+{part}" for part in parts if part not in written)
    meant = base + plain + "".join(f"+{first[rank]}" for rank in sorted(first))
    raise InvalidInputError(
        f"decoder {echo(name)} {problem}: each of {', '.join(labels)} comes at most once, "
        f"in that order ({forms}); did you mean {echo(meant)}?"
    )


def resolve(name: str) -> DecoderSpec:
    """The spec of decoder ``name`` (listed, or parametrized); a clear error lists the
    valid names and refuses a composition out of order (:func:`check_composition`)."""
    check_composition(name)
    specs = _specs()
    if name in specs:
        return specs[name]
    for module in _providers():
        resolver = getattr(module, "resolve", None)
        if resolver is not None and (spec := resolver(name)) is not None:
            return spec
    if meant := plus_read_as_space(name):
        raise InvalidInputError(
            f"unknown decoder {echo(name)}: a URL query reads an unescaped '+' as a space; "
            f"write each '+' as %2B (decoder={quote(meant, safe='')} for {echo(meant)})"
        )
    choices = ", ".join([*specs, *name_patterns()]) or "(none installed)"
    raise InvalidInputError(f"unknown decoder {echo(name)}; choose one of: {choices}")


def plus_read_as_space(name: str) -> str:
    """``name`` with its spaces put back as ``+`` when that names a decoder, else ''.

    A URL query reads an unescaped ``+`` as a space: ``?decoder=herraez+colour`` sends
    the API 'herraez colour'."""
    if " " not in name:
        return ""
    joined = "+".join(name.split())
    try:
        resolve(joined)
    except InvalidInputError:
        return ""
    return joined


def get_decoder(name: str) -> Decoder:
    """The shared instance of decoder ``name``; a clear error lists the valid names. A
    listed decoder's is built once; a parametrized one's is kept among the
    :data:`PARAMETRIZED_KEPT` most recently used."""
    if name in _specs():
        return _listed_decoder(name)
    return _parametrized_decoder(name)


def supporting_decoders(params: SensorParams) -> list[str]:
    """The listed decoders (:func:`available_decoders`) that decode frames with
    ``params`` (:meth:`Decoder.supports`: a learned one only the encodings it has a model
    for), in registration order. Builds each listed decoder (its models load lazily)."""
    return [name for name in _specs() if _listed_decoder(name).supports(params)]


@cache
def _listed_decoder(name: str) -> Decoder:
    return _specs()[name].factory()


@lru_cache(maxsize=PARAMETRIZED_KEPT)
def _parametrized_decoder(name: str) -> Decoder:
    return resolve(name).factory()
