"""Tests of models/errors.py: readable validation errors, caller text echoed cut short."""

from __future__ import annotations

from models.errors import ECHO_CHARS, echo


def test_short_text_is_echoed_whole_and_long_text_cut_with_its_length() -> None:
    assert echo("itho") == "'itho'"
    assert echo("x" * ECHO_CHARS) == repr("x" * ECHO_CHARS)
    cut = echo("x" * 100_000)
    assert cut == f"{'x' * ECHO_CHARS!r}... (and {100_000 - ECHO_CHARS} more characters)"
    assert echo("abcdef", limit=3) == "'abc'... (and 3 more characters)"
