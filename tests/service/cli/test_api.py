"""Tests of ``mcam api``'s settings: flags override the environment, and are blamed as flags."""

from __future__ import annotations

import pytest
from pydantic import ValidationError

from models.errors import InvalidInputError
from service.cli.api import settings_with
from service.core.config import Settings


def test_a_bad_flag_is_named_as_the_flag_not_the_environment() -> None:
    with pytest.raises(InvalidInputError, match=r"^--port 99999: .*65535"):
        settings_with(Settings(), port=99999)


def test_a_good_flag_overrides_and_a_bad_setting_stays_a_settings_error() -> None:
    assert settings_with(Settings(), port=8123, host=None).port == 8123
    with pytest.raises(ValidationError):
        settings_with(Settings.model_construct(port=99999), host="127.0.0.1")
