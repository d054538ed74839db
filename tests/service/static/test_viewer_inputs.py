"""What the viewer tells the API about its inputs and what it shows of the API's answer, in
headless Debian chromium (Playwright, no browser download), against real uvicorn, Redis and
a worker: a scene with negative values (lossy EXR) is simulated once the page asks for them
clipped, a frame read as another format than its name says is noted, and a job not yet
decoded shows no decode facts, a file of the other kind is told which choice takes it, the
file chooser offers every file the API reads, the histogram is named to assistive
technology, an exposure the browser restored is the one the caption names, a tall thin
frame's panels fit the window, a job runs with the decoder chosen when Reconstruct was
pressed, the decoder chosen is kept when the key is saved again, a number typed in exponent
notation is sent as the number it is, and a frame without its parameters is told where they
go on the page.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import pytest

from models.formation import simulate
from models.frames import FRAME_ALIASES, encode_frame
from models.hdr_io import read_hdr
from tests.models.test_frames import png_storing
from tests.service.conftest import PARAMS, exr_bytes, frame_png, npy_bytes, scene
from tests.service.static.conftest import (
    needs_chromium,
    open_viewer,
    wait_for_js,
    wait_for_status,
)
from worker.runner import Worker

if TYPE_CHECKING:
    from playwright.sync_api import Browser, Page, Route

#: A shipped scene: DWAB-compressed (lossy), it holds negative values, as they all do.
SCENE = Path(__file__).resolve().parents[3] / "models" / "data" / "hdri" / "sky.exr"

pytestmark = [pytest.mark.slow, needs_chromium]


def run_and_wait(page: Page) -> str:
    """Press Reconstruct; the status once the page is ready for another run."""
    page.click("#run")
    wait_for_js(page, "!document.getElementById('run').disabled", timeout_ms=60_000)
    return page.inner_text("#status")


def test_a_scene_with_negative_values_is_simulated_once_they_are_clipped(
    browser: Browser, api: str, worker: Worker
) -> None:
    """The API refuses negative scene values unless ``clip_negative`` is sent, and the
    viewer never sent it: no shipped scene could be simulated from the page. Refused,
    the page names the box to tick; ticked, the scene is simulated and reconstructed,
    and the page shows how many values were set to 0 (``X-Mcam-Clipped-Negative``), after
    a reload too."""
    clipped = read_hdr(SCENE, clip_negative=True).negatives_clipped
    assert clipped > 0
    page = open_viewer(browser, api)
    page.check("input[name=kind][value=hdr]")
    page.set_input_files("#file", str(SCENE))
    refused = run_and_wait(page)
    assert page.get_attribute("#status", "class") == "error"
    assert f"{clipped} negative values" in refused, refused
    assert "tick “clip negative values to 0”" in refused, refused
    page.check("#clip-negative")
    assert "succeeded" in run_and_wait(page)
    assert page.is_enabled("#download")
    noted = f"simulate: {clipped} negative scene values set to 0 (clip negative values)"
    assert page.inner_text("#notes") == noted
    page.reload()  # the note is the page's, not the job's: a reload lost it
    wait_for_js(page, "!document.getElementById('download').disabled")
    assert page.inner_text("#notes") == noted


def test_a_frame_read_as_another_format_than_its_name_is_noted(
    browser: Browser, api: str, worker: Worker, tmp_path: Path
) -> None:
    """The API reads a PNG named .tiff as the PNG it is and says so in the job's
    ``warnings``; the page shows them beside the job, and a later job's replace them."""
    misnamed = tmp_path / "frame.tiff"
    misnamed.write_bytes(frame_png(32)[0])
    page = open_viewer(browser, api)
    page.set_input_files("#file", str(misnamed))
    assert "succeeded" in run_and_wait(page)
    notes = page.inner_text("#notes")
    assert notes.startswith("warning: the file's content is PNG although its name"), notes
    assert page.get_attribute("#notes", "class") == "warning"
    named = tmp_path / "frame.png"
    named.write_bytes(misnamed.read_bytes())
    page.set_input_files("#file", str(named))
    page.click("#run")
    wait_for_status(page, "succeeded")
    assert page.inner_text("#notes") == ""


def test_a_job_not_yet_decoded_shows_no_decode_facts(
    browser: Browser, api: str, tmp_path: Path
) -> None:
    """A queued (then cancelled) job's ``info`` is ``{}``: the page's "how the frame was
    decoded" read ``decoder: undefined`` until the job succeeded, and for good when it
    was cancelled or failed. It stays empty until there is something to say."""
    frame = tmp_path / "frame.png"
    frame.write_bytes(frame_png(32)[0])
    page = open_viewer(browser, api)  # no worker: the job stays queued
    page.set_input_files("#file", str(frame))
    page.click("#run")
    wait_for_status(page, "queued")
    assert page.inner_text("#routing") == ""
    page.click("#cancel")
    wait_for_status(page, "cancelled")
    assert page.inner_text("#routing") == ""


def test_a_file_of_the_other_kind_is_told_which_choice_takes_it(
    browser: Browser, api: str, tmp_path: Path
) -> None:
    """An HDR image uploaded as a wrapped frame (the default choice), or a frame as an HDR
    image: the API's 415 says to use mcam simulate or POST /v1/simulate (mcam reconstruct
    or POST /v1/reconstructions), which the page's user does not call; the page now names
    the choice under Upload that takes the file."""
    scene = tmp_path / "scene.exr"
    scene.write_bytes(exr_bytes(32))
    frame = tmp_path / "frame.png"
    frame.write_bytes(frame_png(32)[0])
    page = open_viewer(browser, api)
    page.set_input_files("#file", str(scene))
    refused = run_and_wait(page)
    assert refused.startswith("unsupported_format: "), refused
    assert "not a wrapped frame" in refused and refused.endswith(
        "; if the file is an HDR image, choose “HDR image” under Upload and press Reconstruct"
        " again"
    ), refused
    page.check("input[name=kind][value=hdr]")
    page.set_input_files("#file", str(frame))
    refused = run_and_wait(page)
    assert "if it is a wrapped frame" in refused and refused.endswith(
        "; if the file is a wrapped frame, choose “wrapped frame” under Upload and press"
        " Reconstruct again"
    ), refused


def test_the_file_chooser_offers_every_file_the_api_reads(browser: Browser, api: str) -> None:
    """The chooser's ``accept`` hid Radiance ``.pic`` images, which the API reads as it
    reads ``.hdr`` (by their first bytes)."""
    page = open_viewer(browser, api)
    accept = page.get_attribute("#file", "accept")
    assert accept is not None
    read = [*FRAME_ALIASES, "exr", "hdr", "pic"]  # frames, and HDR images by first bytes
    assert set(accept.split(",")) == {f".{suffix}" for suffix in read}


def test_the_histogram_is_named_to_assistive_technology(browser: Browser, api: str) -> None:
    """The histogram canvas carried an aria-label but no role: a canvas has none of its
    own, so the label was dropped and a screen reader passed over the histogram."""
    page = open_viewer(browser, api)
    histogram = page.get_by_role("img", name="log-luminance histogram")
    assert histogram.count() == 1
    assert histogram.get_attribute("id") == "histogram"


def test_an_exposure_the_browser_restored_is_the_one_the_caption_names(
    browser: Browser, api: str
) -> None:
    """Back to the page, the browser restores the slider where it was (-4 EV), and the
    previews were made at it, but the caption read "tonemapped at 0 EV" until the slider
    moved."""
    page = open_viewer(browser, api)
    page.fill("#exposure", "-4")
    page.dispatch_event("#exposure", "input")
    page.goto("about:blank")
    page.go_back()
    wait_for_js(page, "document.getElementById('exposure').value === '-4'")
    wait_for_js(page, "document.getElementById('ev-value').textContent === '-4'")


def test_a_tall_thin_frame_s_panels_fit_the_window(
    browser: Browser, api: str, worker: Worker, tmp_path: Path
) -> None:
    """A 256 x 2 frame (valid: at least 2 x 2) was drawn 100% wide, so each panel stood
    over 50 000 px tall, the exposure slider, histogram and Download far below it."""
    frame = simulate(scene(256)[:, :2].copy(), PARAMS)
    tall = tmp_path / "tall.png"
    tall.write_bytes(encode_frame(frame.codes, frame.params, "png"))
    page = open_viewer(browser, api)
    page.set_viewport_size({"width": 1280, "height": 800})
    page.set_input_files("#file", str(tall))
    assert "succeeded" in run_and_wait(page)
    wait_for_js(page, "!document.getElementById('download').disabled")
    heights = page.evaluate(
        "['img-codes', 'img-winding', 'img-hdr']"
        ".map(id => document.getElementById(id).getBoundingClientRect().height)"
    )
    assert max(heights) <= 800, f"panels {heights} px tall in an 800 px window"


def test_the_decoder_is_the_one_chosen_when_reconstruct_was_pressed(
    browser: Browser, api: str, tmp_path: Path
) -> None:
    """An HDR image is simulated first; the decoder or quality was read only once the
    simulate came back, so one changed meanwhile (set up for the next run) ran this job."""
    scene = tmp_path / "scene.exr"
    scene.write_bytes(exr_bytes(32))
    page = open_viewer(browser, api)  # no worker: only the submit is looked at
    held: list[Route] = []
    page.route("**/v1/simulate", lambda route: held.append(route))
    page.check("input[name=kind][value=hdr]")
    page.set_input_files("#file", str(scene))
    page.select_option("#quality", "fast")
    page.click("#run")
    wait_for_js(page, "document.getElementById('status').textContent.includes('simulating')")
    while not held:
        page.wait_for_timeout(50)
    page.select_option("#quality", "best")
    with page.expect_request("**/v1/reconstructions") as submitted:
        held[0].continue_()
    body = submitted.value.post_data_buffer or b""
    assert b'name="quality"\r\n\r\nfast\r\n' in body, body[-400:]
    wait_for_status(page, "queued")


def test_a_frame_without_its_parameters_is_told_where_to_give_them_on_the_page(
    browser: Browser, api: str, tmp_path: Path
) -> None:
    """An npy frame stores no encoding, alpha or bits: the API's refusal names the
    command line's flags and the HTTP form fields, neither of which the page's user
    sends; the page adds where they go on it."""
    frame = tmp_path / "frame.npy"
    frame.write_bytes(npy_bytes(np.zeros((8, 8), dtype=np.uint8)))
    page = open_viewer(browser, api)
    page.set_input_files("#file", str(frame))
    refused = run_and_wait(page)
    assert refused.startswith("missing_parameter: the frame does not store its"), refused
    assert refused.endswith(
        "; on this page, fill in encoding, alpha and bits under Sensor and press Reconstruct"
        " again"
    ), refused


def test_a_number_in_exponent_notation_is_sent_as_the_number_it_is(
    browser: Browser, api: str, worker: Worker, tmp_path: Path
) -> None:
    """The browser takes bits "8e0" as the number 8, but the page sent the text as typed
    and the API refused it: "bits: Input should be a valid integer"."""
    frame = tmp_path / "frame.npy"
    frame.write_bytes(npy_bytes(np.zeros((8, 8), dtype=np.uint8)))
    page = open_viewer(browser, api)
    page.set_input_files("#file", str(frame))
    page.select_option("#encoding", "modulo")
    page.fill("#bits", "8e0")
    page.fill("#alpha", "2e0")
    status = run_and_wait(page)
    assert status.endswith(": succeeded"), status


def test_the_decoder_chosen_is_kept_when_the_key_is_saved_again(
    browser: Browser, api: str
) -> None:
    """Save key lists the decoders again, and put the server's default in place of the
    one chosen, unsaid: the next run used the default."""
    page = open_viewer(browser, api)
    page.select_option("#decoder", "herraez")  # not the default
    page.click("#key-form button")
    wait_for_status(page, "API key saved")
    wait_for_js(page, "document.getElementById('decoder').options.length > 1")
    assert page.input_value("#decoder") == "herraez"


#: The page's hint for a frame refused for the parameters it lacks, after the field names.
SENSOR_HINT = " under Sensor and press Reconstruct again"


def test_a_frame_whose_stored_parameters_are_unreadable_is_told_which_to_fill_in(
    browser: Browser, api: str, tmp_path: Path
) -> None:
    """A PNG whose parameter chunk is no JSON is refused ``invalid_input``, naming the
    flags and form fields to give instead: the page added no word of its Sensor fields,
    as it did for ``missing_parameter``. It now names the fields the refusal asks for,
    and none where one of them is not on the page (a stored read noise out of range)."""
    broken = tmp_path / "broken.png"
    broken.write_bytes(png_storing("{broken"))
    page = open_viewer(browser, api)
    page.set_input_files("#file", str(broken))
    refused = run_and_wait(page)
    assert refused.startswith("invalid_input: the PNG text chunk is not valid JSON"), refused
    assert refused.endswith(f"; on this page, fill in encoding, alpha and bits{SENSOR_HINT}")
    page.select_option("#encoding", "mantissa")
    assert run_and_wait(page).endswith(f"; on this page, fill in alpha and bits{SENSOR_HINT}")

    noisy = tmp_path / "noisy.png"
    noisy.write_bytes(png_storing('{"alpha": 2, "bits": 8, "read_noise": 5}'))
    page.set_input_files("#file", str(noisy))
    refused = run_and_wait(page)
    assert refused.startswith("invalid_input: invalid sensor parameters: read_noise"), refused
    assert "on this page" not in refused, refused

    page.set_input_files("#file", str(broken))
    page.fill("#alpha", "2")
    page.fill("#bits", "8")
    page.click("#run")
    wait_for_status(page, "queued")  # no worker: the job waits
