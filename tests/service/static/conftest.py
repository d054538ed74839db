"""Helpers of the browser tests: Debian's chromium launched headless, and waiting on the
page under the viewer's CSP."""

from __future__ import annotations

import shutil
import time
from collections.abc import Iterator
from contextlib import contextmanager
from typing import TYPE_CHECKING, Any

import pytest

from tests.service.conftest import FULL_KEY

if TYPE_CHECKING:
    from playwright.sync_api import Browser, Page

#: Debian's chromium (Playwright never downloads a browser here).
CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
#: A browser test is skipped without chromium.
needs_chromium = pytest.mark.skipif(
    CHROMIUM is None,
    reason="Debian chromium is not installed (apt-get install -y chromium); "
    "the browser test needs it",
)

#: How often a wait re-evaluates its expression (ms).
POLL_MS = 50


def wait_for_js(page: Page, expression: str, arg: Any = None, timeout_ms: int = 30_000) -> Any:
    """Poll a JavaScript expression (or a function of ``arg``) until it is truthy, and
    return that value.

    ``page.wait_for_function`` compiles its predicate in the page with ``new Function``,
    which the viewer's Content Security Policy forbids (no ``'unsafe-eval'``);
    ``page.evaluate`` runs through the DevTools protocol, which the policy allows.
    """
    deadline = time.monotonic() + timeout_ms / 1000
    evaluate = (lambda: page.evaluate(expression)) if arg is None else (
        lambda: page.evaluate(expression, arg)
    )
    while not (value := evaluate()):
        if time.monotonic() > deadline:
            pytest.fail(f"not true within {timeout_ms} ms: {expression}")
        page.wait_for_timeout(POLL_MS)
    return value


@contextmanager
def chromium() -> Iterator[Browser]:
    """Headless Debian chromium under Playwright (the test is skipped without Playwright)."""
    sync_api = pytest.importorskip("playwright.sync_api")
    with sync_api.sync_playwright() as playwright:
        browser = playwright.chromium.launch(
            executable_path=CHROMIUM, args=["--no-sandbox", "--disable-gpu"]
        )
        try:
            yield browser
        finally:
            browser.close()


def open_viewer(browser: Browser, url: str, *, fake_clock: bool = False) -> Page:
    """The viewer at ``url`` with the key saved and the decoders listed; with
    ``fake_clock`` the page's timers are Playwright's fake clock, which the test moves
    on (``page.clock.run_for``) and which also goes on at the wall clock's pace."""
    page = browser.new_page()
    page.set_default_timeout(30_000)
    if fake_clock:
        page.clock.install()
    page.goto(f"{url}/")
    page.fill("#api-key", FULL_KEY)
    page.click("#key-form button")
    page.wait_for_selector("#decoder option[value=itoh]", state="attached")
    return page


def wait_for_status(page: Page, text: str, timeout_ms: int = 30_000) -> str:
    """The page's status line as it read when it first held ``text``: read in the same
    evaluation, since the page's timers run on (a read after the wait could see the next
    status, as a retry's answer replaced "connection to the server lost")."""
    return wait_for_js(
        page,
        "(text) => { const status = document.getElementById('status').innerText;"
        " return status.includes(text) ? status : null; }",
        text,
        timeout_ms=timeout_ms,
    )


@pytest.fixture
def browser() -> Iterator[Browser]:
    """Headless Debian chromium for the test (see :func:`chromium`)."""
    with chromium() as launched:
        yield launched
