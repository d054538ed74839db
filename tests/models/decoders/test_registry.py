"""Decoder lookup (models/decoders/registry.py): cached instances, clear errors."""

from __future__ import annotations

import gc
import weakref

import pytest

from models.decoders.base import Decoder
from models.decoders.classical import HerraezDecoder, ItohDecoder
from models.decoders.registry import (
    PARAMETRIZED_KEPT,
    available_decoders,
    get_decoder,
    resolve,
    supporting_decoders,
)
from models.errors import InvalidInputError
from models.formation import SensorParams


def test_classical_decoders_are_available_first() -> None:
    specs = available_decoders()
    names = [spec.name for spec in specs]
    assert names[:2] == ["itoh", "herraez"]
    assert len(names) == len(set(names))
    assert all(spec.description for spec in specs)


@pytest.mark.parametrize(("name", "cls"), [("itoh", ItohDecoder), ("herraez", HerraezDecoder)])
def test_get_decoder_returns_one_cached_instance(name: str, cls: type[Decoder]) -> None:
    decoder = get_decoder(name)
    assert isinstance(decoder, cls)
    assert decoder.name == name
    assert get_decoder(name) is decoder


def test_parametrized_decoders_kept_are_bounded() -> None:
    """Every latency budget a request named (``latency_ms`` is any number) stayed built
    for the life of the worker: 500 budgets kept 500 decoders."""
    itoh = get_decoder("itoh")
    names = [f"auto-{budget}ms" for budget in range(1, 501)] + [
        f"itoh+puma{moves}" for moves in range(1, 501)
    ]
    built = [weakref.ref(get_decoder(name)) for name in names]
    gc.collect()
    assert sum(ref() is not None for ref in built) == PARAMETRIZED_KEPT
    assert get_decoder(names[-1]) is built[-1]()  # the recently used is shared
    assert get_decoder("itoh") is itoh  # listed decoders are never dropped


def test_every_available_decoder_builds() -> None:
    for spec in available_decoders():
        assert isinstance(get_decoder(spec.name), Decoder)


def test_unknown_decoder_lists_the_valid_names() -> None:
    with pytest.raises(
        InvalidInputError, match=r"unknown decoder 'itho'; choose one of: itoh, herraez"
    ):
        get_decoder("itho")


@pytest.mark.parametrize(
    ("name", "escaped"),
    [
        ("herraez colour", "herraez%2Bcolour"),
        ("mantissanet-small puma colour", "mantissanet-small%2Bpuma%2Bcolour"),
    ],
)
def test_a_plus_a_url_query_read_as_a_space_is_named(name: str, escaped: str) -> None:
    """``?decoder=herraez+colour`` reaches the API as 'herraez colour': the refusal says
    to write the '+' as %2B instead of listing every decoder."""
    with pytest.raises(InvalidInputError) as caught:
        resolve(name)
    message = str(caught.value)
    assert "reads an unescaped '+' as a space" in message
    assert f"decoder={escaped}" in message
    assert "choose one of" not in message


def test_a_spaced_name_that_names_no_decoder_lists_the_valid_names() -> None:
    with pytest.raises(InvalidInputError, match=r"unknown decoder 'itho colour'; choose one"):
        resolve("itho colour")


@pytest.mark.parametrize(
    ("name", "problem", "meant"),
    [
        ("graphcut+puma+colour+puma", "repeats +puma", "graphcut+puma+colour"),
        ("herraez+colour+puma", "puts +colour before +puma", "herraez+puma+colour"),
        ("itoh+colour+colour", "repeats +colour", "itoh+colour"),
        ("itoh+puma2+puma", "repeats +puma", "itoh+puma2"),
    ],
)
def test_suffixes_repeated_or_out_of_order_are_refused_with_the_valid_forms(
    name: str, problem: str, meant: str
) -> None:
    """graphcut+puma+colour+puma was accepted (and decoded: PUMA twice)."""
    with pytest.raises(InvalidInputError) as error:
        resolve(name)
    assert error.value.message == (
        f"decoder {name!r} {problem}: each of +puma, +colour comes at most once, in that "
        "order (<decoder>, <decoder>+colour, <decoder>+puma, <decoder>+puma+colour); did "
        f"you mean {meant!r}?"
    )
    assert resolve(meant).name == meant


def test_an_unknown_decoder_is_echoed_cut_short() -> None:
    """A 100 KB name came back whole in a 101 KB error."""
    with pytest.raises(InvalidInputError) as error:
        resolve("x" * 100_000)
    message = error.value.message
    assert message.startswith(f"unknown decoder {'x' * 80!r}... (and 99920 more characters);")
    assert len(message) < 2_000 and "choose one of: itoh" in message


def test_supporting_decoders_leave_out_those_without_a_model_for_the_encoding() -> None:
    """The noise-aware nets have mantissa models only: they are no choice for modulo
    frames, while any decoder decodes frames of a sensor that never wraps."""
    listed = [spec.name for spec in available_decoders()]
    modulo = supporting_decoders(SensorParams(encoding="modulo", bits=8))
    assert modulo == [name for name in listed if "-noise" not in name]
    assert {"itoh", "mantissanet-tiny", "auto"} <= set(modulo)
    assert supporting_decoders(SensorParams(encoding="clip", bits=8)) == listed
