"""The web viewer end to end in headless Debian chromium (Playwright, no browser download).

Real uvicorn on 127.0.0.1, real Redis, a real worker: upload an HDR image, simulate,
reconstruct, watch the job, move the exposure slider, download the EXR. The
screenshot is kept in ``artifacts/`` (gitignored) for people to look at.
"""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest

from models.hdr_io import encode_exr, read_hdr
from tests.service.conftest import FULL_KEY
from tests.service.conftest import scene as scene_irradiance
from tests.service.static.conftest import chromium, needs_chromium, wait_for_js
from worker.runner import Worker

ARTIFACTS = Path(__file__).resolve().parents[3] / "artifacts"

pytestmark = [pytest.mark.slow, needs_chromium]


def test_simulate_reconstruct_and_inspect(api: str, worker: Worker, tmp_path: Path) -> None:
    """A colour EXR (every Radiance .hdr is colour too): its simulated frame travels as a
    TIFF (a PNG frame is grey only, and colour HDR images used to fail here)."""
    scene = tmp_path / "scene.exr"
    grey = scene_irradiance(128)
    scene.write_bytes(encode_exr(np.stack([grey, 0.8 * grey, 0.6 * grey], axis=2)))
    with chromium() as browser:
        page = browser.new_page(viewport={"width": 1280, "height": 900}, accept_downloads=True)
        errors: list[str] = []
        page.on("pageerror", lambda exc: errors.append(str(exc)))
        page.on(  # a missing favicon, a failed request: each logs a console error
            "console",
            lambda message: errors.append(message.text) if message.type == "error" else None,
        )
        page.goto(f"{api}/")
        page.fill("#api-key", FULL_KEY)
        page.click("#key-form button")
        page.wait_for_selector("#decoder option[value=itoh]", state="attached")
        assert page.evaluate("localStorage.getItem('mcam-api-key')") == FULL_KEY
        page.check("input[name=kind][value=hdr]")
        page.set_input_files("#file", str(scene))
        page.select_option("#encoding", "mantissa")
        page.fill("#alpha", "2")
        page.fill("#bits", "8")
        page.select_option("#quality", "balanced")
        page.click("#run")
        wait_for_js(page, "!document.getElementById('download').disabled", timeout_ms=60_000)
        assert "succeeded" in page.inner_text("#status")
        routing = page.inner_text("#routing")
        assert routing.startswith("decoder: auto-balanced") and "%" in routing
        wait_for_js(  # blob images decode asynchronously
            page,
            "['img-codes', 'img-winding', 'img-hdr'].every(id => {"
            " const image = document.getElementById(id);"
            " return image.complete && image.naturalWidth === 128; })",
            timeout_ms=30_000,
        )
        before = page.get_attribute("#img-hdr", "src")
        page.fill("#exposure", "-4")
        page.dispatch_event("#exposure", "input")
        wait_for_js(page, f"document.getElementById('img-hdr').src !== '{before}'")
        assert page.inner_text("#ev-value") == "-4"
        with page.expect_download() as download:
            page.click("#download")
        exr = tmp_path / "result.exr"
        download.value.save_as(exr)
        assert read_hdr(exr).pixels.shape == (128, 128, 3)
        shot = tmp_path / "viewer.png"
        page.screenshot(path=str(shot), full_page=True)
    ARTIFACTS.mkdir(exist_ok=True)
    shutil.copy(shot, ARTIFACTS / "viewer.png")
    assert errors == []
