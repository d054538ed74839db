"""Helpers of the browser tests: waiting on the page under the viewer's CSP."""

from __future__ import annotations

import time
from typing import TYPE_CHECKING, Any

import pytest

if TYPE_CHECKING:
    from playwright.sync_api import Page

#: How often a wait re-evaluates its expression (ms).
POLL_MS = 50


def wait_for_js(page: Page, expression: str, arg: Any = None, timeout_ms: int = 30_000) -> None:
    """Poll a JavaScript expression (or a function of ``arg``) until it is truthy.

    ``page.wait_for_function`` compiles its predicate in the page with ``new Function``,
    which the viewer's Content Security Policy forbids (no ``'unsafe-eval'``);
    ``page.evaluate`` runs through the DevTools protocol, which the policy allows.
    """
    deadline = time.monotonic() + timeout_ms / 1000
    while not (page.evaluate(expression) if arg is None else page.evaluate(expression, arg)):
        if time.monotonic() > deadline:
            pytest.fail(f"not true within {timeout_ms} ms: {expression}")
        page.wait_for_timeout(POLL_MS)
