"""service/api/state.py: what an API process opens at startup."""

from __future__ import annotations

import logging
from pathlib import Path

import pytest

from service.api.state import open_state
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
