"""Decoder lookup (models/decoders/registry.py): cached instances, clear errors."""

from __future__ import annotations

import pytest

from models.decoders.base import Decoder
from models.decoders.classical import HerraezDecoder, ItohDecoder
from models.decoders.registry import available_decoders, get_decoder
from models.errors import InvalidInputError


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


def test_every_available_decoder_builds() -> None:
    for spec in available_decoders():
        assert isinstance(get_decoder(spec.name), Decoder)


def test_unknown_decoder_lists_the_valid_names() -> None:
    with pytest.raises(
        InvalidInputError, match=r"unknown decoder 'itho'; choose one of: itoh, herraez"
    ):
        get_decoder("itho")
