"""service/api/state.py: what an API process opens at startup."""

from __future__ import annotations

import asyncio
import logging
from pathlib import Path

import pytest

from service.api.state import Slots, open_state
from service.core.security import KeyRing
from tests.service.conftest import make_settings
from worker.embedded_redis import EmbeddedRedis, connect


def test_a_redis_that_could_lose_accepted_jobs_is_warned_about(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    with EmbeddedRedis(tmp_path / "external") as url:
        settings = make_settings(tmp_path, url)
        with caplog.at_level(logging.WARNING, logger="service.api.state"):
            open_state(settings, KeyRing.from_settings(settings)[0]).close()
        assert not caplog.records  # appendfsync always: nothing to say
        connect(url).config_set("appendfsync", "everysec")
        with caplog.at_level(logging.WARNING, logger="service.api.state"):
            open_state(settings, KeyRing.from_settings(settings)[0]).close()
        [warning] = caplog.records
        assert "may lose accepted jobs" in warning.getMessage()
        assert "appendfsync always" in warning.getMessage()


def test_a_slot_freed_while_a_request_waits_is_taken_by_it() -> None:
    slots = Slots(1)
    assert slots.take()

    async def wait_for_the_release() -> None:
        waiting = asyncio.ensure_future(slots.wait_take(30))
        await asyncio.sleep(0)  # it looked once and found none free
        assert not waiting.done()
        slots.release()
        assert await waiting

    asyncio.run(wait_for_the_release())
    assert slots.full


def test_a_request_waits_for_a_slot_no_longer_than_asked() -> None:
    slots = Slots(1)
    assert slots.take()
    assert not asyncio.run(slots.wait_take(0.1))
    assert not asyncio.run(slots.wait_take(0))
    slots.release()
    assert asyncio.run(slots.wait_take(0)) and slots.full
