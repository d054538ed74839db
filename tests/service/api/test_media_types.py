"""Tests of service/api/media_types.py: the declared media type, bare and lower case."""

from __future__ import annotations

import pytest
from starlette.requests import Request

from service.api.media_types import media_type


def request_with(headers: list[tuple[bytes, bytes]]) -> Request:
    return Request({"type": "http", "method": "POST", "path": "/", "headers": headers})


@pytest.mark.parametrize(
    ("header", "expected"),
    [
        (b"application/json", "application/json"),
        (b"Multipart/Form-Data; boundary=x", "multipart/form-data"),
        (b" text/plain ; charset=utf-8", "text/plain"),
    ],
)
def test_parameters_and_case_are_dropped(header: bytes, expected: str) -> None:
    assert media_type(request_with([(b"content-type", header)])) == expected


def test_no_header_is_empty() -> None:
    assert media_type(request_with([])) == ""
