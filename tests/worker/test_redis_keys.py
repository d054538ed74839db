"""Tests of worker/redis_keys.py: every key name in one place, device ids checked."""

from __future__ import annotations

import pytest
from hypothesis import given
from hypothesis import strategies as st

from models.errors import InvalidInputError
from worker.redis_keys import (
    control_stream,
    events_stream,
    frame_stream,
    health_key,
    lease_key,
    rate_limit_key,
    recording_key,
    validate_device_id,
)

DEVICE_KEYS = (frame_stream, health_key, control_stream, events_stream, lease_key, recording_key)


@given(st.from_regex(r"[A-Za-z0-9_-]{1,64}", fullmatch=True))
def test_valid_device_ids_name_distinct_keys(device: str) -> None:
    names = [key(device) for key in DEVICE_KEYS]
    assert len(set(names)) == len(names) and all(device in name for name in names)


@pytest.mark.parametrize("device", ["", "a b", "x" * 65, "../etc", "cam:1", "ca\nm"])
def test_invalid_device_ids_are_refused_with_the_rule(device: str) -> None:
    with pytest.raises(InvalidInputError, match="1-64 letters, digits"):
        validate_device_id(device)
    with pytest.raises(InvalidInputError):
        frame_stream(device)


@pytest.mark.parametrize("device", ["caméra", "cam\u0661"])
def test_an_id_of_other_scripts_letters_or_digits_is_told_to_use_ascii(device: str) -> None:
    """'caméra' was told to use letters, digits, '_' or '-', which it does."""
    with pytest.raises(InvalidInputError, match=r"\(ASCII: A-Z, a-z, 0-9\)"):
        validate_device_id(device)


def test_a_long_invalid_device_id_is_echoed_cut_short() -> None:
    with pytest.raises(InvalidInputError) as error:
        validate_device_id("a b" * 10_000)
    assert "(and 29920 more characters): use 1-64 letters" in error.value.message
    assert len(error.value.message) < 200


def test_rate_limit_keys_hold_the_key_id_only() -> None:
    assert rate_limit_key("0123abcd") == "ratelimit:0123abcd"
