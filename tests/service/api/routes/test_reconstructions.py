"""POST /v1/reconstructions against a live API, a real Redis and a real worker."""

from __future__ import annotations

import io
import os
import signal
import threading
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import OpenEXR
import pytest
from PIL import Image

from models.frames import encode_frame
from models.hdr_io import read_hdr
from service.api.routes.jobs import PART_FORMATS
from service.api.routes.reconstructions import prefer_wait_s
from service.api.state import Slots
from service.main import create_app
from tests.models.test_frames import miniswhite_tiff, png_storing, with_masks
from tests.service.conftest import (
    FULL_KEY,
    PARAMS,
    READ_KEY,
    SUBMIT_KEY,
    exr_bytes,
    finished_job,
    frame_png,
    make_settings,
    npy_bytes,
    running_worker,
    serve,
)
from worker.embedded_redis import EmbeddedRedis, connect
from worker.redis_keys import JOBS_STREAM
from worker.runner import Worker

Client = Callable[[str], httpx.Client]


def kill_once_waiting(slots: Slots, pid: int, timeout_s: float = 60.0) -> None:
    """SIGKILL process ``pid`` once a request holds the one wait slot of ``slots`` (its
    job is queued and it waits for it), or after ``timeout_s``."""
    deadline = time.monotonic() + timeout_s
    while not slots.full and time.monotonic() < deadline:
        time.sleep(0.01)
    os.kill(pid, signal.SIGKILL)


def test_a_wait_cut_short_by_redis_answers_202_for_the_accepted_job(tmp_path: Path) -> None:
    """Redis dies while a submit waits for its job (no worker runs): the job is stored,
    so the answer is its 202, not a 503 that would have the client submit it twice.
    Once Redis is back (its append-only file kept the job) the job is there, queued.
    Redis is killed once the submit waits (a kill 1 s after the start came before the
    submit on a loaded machine: a 503 for a job never stored)."""
    embedded = EmbeddedRedis(tmp_path / "redis-home")
    with embedded as redis_url:
        app = create_app(make_settings(tmp_path, redis_url, max_waiting_requests=1))
        with serve(app) as url, httpx.Client(
            base_url=url, headers={"Authorization": f"Bearer {FULL_KEY}"}
        ) as http:
            pid = embedded.pid
            assert pid is not None
            threading.Thread(target=kill_once_waiting, args=(app.state.mcam.wait_slots, pid),
                             daemon=True).start()
            data, _ = frame_png()
            reply = http.post(
                "/v1/reconstructions", files={"file": ("frame.png", data, "image/png")},
                headers={"Prefer": "wait=30"}, timeout=60,
            )  # fmt: skip
            assert reply.status_code == 202, reply.text
            job = reply.json()
            assert reply.headers["Location"] == job["url"] == f"/v1/jobs/{job['id']}"
            embedded.stop()
            embedded.start()
            assert http.get(job["url"]).json()["state"] == "queued"


def test_prefer_wait_returns_the_finished_job(client: Client, worker: Worker) -> None:
    data, _ = frame_png()
    reply = client().post(
        "/v1/reconstructions",
        files={"file": ("frame.png", data, "image/png")},
        data={"decoder": "itoh"},
        headers={"Prefer": "wait=20"},
    )
    assert reply.status_code == 200, reply.text
    job = reply.json()
    assert job["state"] == "succeeded"
    assert job["decoder"] == "itoh"
    assert set(job["timings_ns"]) >= {"decode", "encode"}
    assert job["links"]["result"] == f"/v1/jobs/{job['id']}/result"
    assert reply.headers["Location"] == f"/v1/jobs/{job['id']}"


def test_a_wait_in_a_second_prefer_line_is_read(client: Client, worker: Worker) -> None:
    """RFC 7240 lets a client send its preferences on several ``Prefer`` lines: only the
    first was read, so ``respond-async`` then ``wait=20`` got 202 at once."""
    data, _ = frame_png()
    reply = client().post(
        "/v1/reconstructions",
        files={"file": ("frame.png", data, "image/png")},
        data={"decoder": "itoh"},
        headers=[("Prefer", "respond-async"), ("Prefer", "wait=20")],
    )
    assert reply.status_code == 200, reply.text
    assert reply.json()["state"] == "succeeded"
    assert reply.headers["Preference-Applied"] == "wait=20"


def test_a_prefer_wait_longer_than_the_servers_limit_is_cut_to_it(
    tmp_path: Path, redis_url: str
) -> None:
    """``Prefer: wait=600`` under ``MCAM_MAX_PREFER_WAIT_S`` 30 waits 30 s at the most: the
    applied preference names the limit, not the asked-for 600 s."""
    settings = make_settings(tmp_path, redis_url, max_prefer_wait_s=30.0)
    data, _ = frame_png()
    with serve(create_app(settings)) as url, running_worker(settings):
        reply = httpx.post(
            f"{url}/v1/reconstructions",
            files={"file": ("f.png", data)},
            data={"decoder": "itoh"},
            timeout=60,
            headers={"Authorization": f"Bearer {FULL_KEY}", "Prefer": "wait=600"},
        )
    assert reply.status_code == 200, reply.text
    assert reply.headers["Preference-Applied"] == "wait=30"


def test_without_prefer_the_job_is_accepted(client: Client) -> None:
    data, _ = frame_png()
    reply = client(SUBMIT_KEY).post(
        "/v1/reconstructions", files={"file": ("f.png", data)}, data={"quality": "fast"}
    )
    assert reply.status_code == 202, reply.text
    body = reply.json()
    assert body["url"] == f"/v1/jobs/{body['id']}" and body["state"] == "queued"


def test_a_latency_budget_picks_a_routing_and_reports_it(client: Client, worker: Worker) -> None:
    data, _ = frame_png()
    reply = client().post(
        "/v1/reconstructions",
        files={"file": ("frame.png", data, "image/png")},
        data={"latency_ms": "5000"},
        headers={"Prefer": "wait=60"},
    )
    assert reply.status_code == 200, reply.text
    job = reply.json()
    assert job["state"] == "succeeded" and job["decoder"] == "auto-5000ms"
    assert job["info"]["details"]["budget"]["budget_ms"] == 5000.0


def test_exr_compression_is_a_choice_of_the_request(client: Client, worker: Worker) -> None:
    data, _ = frame_png()
    results = {}
    for compression in ("zip", "none"):
        reply = client().post(
            "/v1/reconstructions",
            files={"file": ("frame.png", data, "image/png")},
            data={"decoder": "itoh", "exr_compression": compression},
            headers={"Prefer": "wait=20"},
        )
        assert reply.status_code == 200, reply.text
        result = client().get(reply.json()["links"]["result"])
        assert result.status_code == 200
        results[compression] = result.content
    headers = {
        name: OpenEXR.File(io.BytesIO(content), header_only=True).header()
        for name, content in results.items()
    }
    assert headers["zip"]["compression"] == OpenEXR.ZIP_COMPRESSION
    assert headers["none"]["compression"] == OpenEXR.NO_COMPRESSION
    assert len(results["none"]) > len(results["zip"])
    np.testing.assert_array_equal(
        read_hdr(results["none"]).pixels, read_hdr(results["zip"]).pixels
    )


def test_raw_body_with_query_parameters(client: Client, worker: Worker) -> None:
    _, codes = frame_png()
    reply = client().post(
        "/v1/reconstructions",
        content=codes.tobytes(),
        params={"width": 64, "height": 64, "bits": 8, "encoding": "mantissa", "alpha": 2},
        headers={"Content-Type": "application/octet-stream", "Prefer": "wait=20"},
    )
    assert reply.status_code == 200, reply.text
    assert reply.json()["params"]["bits"] == 8


@pytest.mark.parametrize(
    ("kwargs", "status", "code"),
    [
        (
            {"content": b"\x89PNG\r\n\x1a\nbroken", "params": {"format": "png"}},
            422,
            "invalid_input",
        ),
        ({"content": b"hello", "params": {}}, 415, "unsupported_format"),
        (
            {"content": bytes(100), "params": {"format": "raw", "width": 8, "height": 8}},
            422,
            "missing_parameter",
        ),
        (
            {
                "content": bytes(63),
                "params": {
                    "format": "raw",
                    "width": 8,
                    "height": 8,
                    "bits": 8,
                    "encoding": "modulo",
                },
            },
            422,
            "invalid_input",
        ),
    ],
)
def test_bad_raw_uploads(client: Client, kwargs: dict, status: int, code: str) -> None:
    reply = client().post(
        "/v1/reconstructions", headers={"Content-Type": "application/octet-stream"}, **kwargs
    )
    assert reply.status_code == status, reply.text
    assert reply.json()["code"] == code


def test_a_png_sent_as_raw_codes_is_named_as_a_png(client: Client) -> None:
    """A PNG named .bin with a raw size was told only that its byte count is wrong for
    the size: 'check the size and bit depth'."""
    data, _ = frame_png()
    reply = client().post("/v1/reconstructions", files={"file": ("frame.bin", data)},
                          data={"width": "8", "height": "8", "bits": "8"})
    assert reply.status_code == 422, reply.text
    message = reply.json()["message"]
    assert "is 64 bytes (1 per code)" in message
    assert "its first bytes are a PNG file's" in message and "without format=raw" in message


@pytest.mark.parametrize("field", ["latency_ms", "gain", "read_noise"])
def test_a_nan_parameter_is_named_as_not_finite(client: Client, field: str) -> None:
    reply = client().post(
        "/v1/reconstructions",
        headers={"Content-Type": "application/octet-stream"},
        content=bytes(64),
        params={"format": "raw", "width": 8, "height": 8, "bits": 8, "encoding": "modulo",
                field: "nan"},
    )
    assert reply.status_code == 422, reply.text
    assert f"{field}: Input should be a finite number" in reply.json()["message"]


@pytest.mark.parametrize(
    ("fields", "code", "fragment"),
    [
        ({"max_wraps": "1e-300"}, "invalid_input", "max_wraps: must be at least 1 wrap"),
        ({"gain": "1e-320"}, "output_overflow", "whatever winding numbers a decoder finds"),
        ({"gain": "1e308", "max_wraps": "16"}, "output_underflow",
         "whatever winding numbers a decoder finds"),
        ({"gain": "1e-30", "half": "true"}, "output_overflow",
         "ask for float32 output instead of half floats"),
        ({"gain": "1e-300", "half": "true"}, "output_overflow",
         "float16 limit 6.55e+04; float32 output cannot hold them either: the output is "
         "scene-referred x / gain with gain 1e-300"),
        ({"gain": "1e308", "max_wraps": "16", "half": "true"}, "output_underflow",
         "float32 output would store them as 0 too"),
    ],
)  # fmt: skip
def test_parameters_that_cannot_give_a_result_are_refused_at_submit(
    client: Client, redis_url: str, fields: dict[str, str], code: str, fragment: str
) -> None:
    """max_wraps 1e-300 gave a job that succeeded with W = 0 everywhere; gain 1e-320 or
    1e308 a job the worker failed (output_overflow / output_underflow) after decoding."""
    data, _ = frame_png()
    reply = client().post("/v1/reconstructions", files={"file": ("f.png", data)}, data=fields)
    assert reply.status_code == 422, reply.text
    assert reply.json()["code"] == code and fragment in reply.json()["message"]
    assert connect(redis_url).xlen(JOBS_STREAM) == 0


def test_codes_above_bit_depth_are_refused(client: Client) -> None:
    codes = np.full((8, 8), 300, np.uint16)
    reply = client().post(
        "/v1/reconstructions",
        content=codes.tobytes(),
        params={"format": "raw", "width": 8, "height": 8, "bits": 16, "encoding": "modulo"},
        headers={"Content-Type": "application/octet-stream"},
    )
    assert reply.status_code == 202
    reply = client().post(
        "/v1/reconstructions",
        files={"file": ("f.npy", npy_bytes(codes))},
        data={"bits": "8", "encoding": "modulo"},
    )
    assert reply.status_code == 422
    assert "2^8" in reply.json()["message"]


def test_float_codes_are_refused(client: Client) -> None:
    reply = client().post(
        "/v1/reconstructions",
        files={"file": ("f.npy", npy_bytes(np.zeros((8, 8), np.float32)))},
        data={"bits": "8", "encoding": "modulo"},
    )
    assert reply.status_code == 422
    assert "dtype" in reply.json()["message"]


def test_missing_parameters_name_the_form_fields(client: Client) -> None:
    reply = client().post(
        "/v1/reconstructions", files={"file": ("f.npy", npy_bytes(np.zeros((8, 8), np.uint8)))}
    )
    assert reply.status_code == 422
    body = reply.json()
    assert body["code"] == "missing_parameter"
    assert "form fields encoding=mantissa, bits=8" in body["message"]


@pytest.mark.parametrize(
    ("stored", "given", "asked"),
    [(None, {}, ["encoding", "bits", "alpha"]),
     ("{broken", {}, ["encoding", "bits", "alpha"]),  # unreadable: invalid_input
     ("{broken", {"encoding": "mantissa"}, ["bits", "alpha"]),
     ('{"encoding": "modulo", "bits": 8, "read_noise": 5}', {}, ["read_noise"])],
)  # fmt: skip
def test_a_refusal_asking_for_parameters_names_them(
    client: Client, stored: str | None, given: dict[str, str], asked: list[str]
) -> None:
    """The refusal's ``parameters`` name the form fields its message asks for, so that a
    client (the viewer) can point at its own: a frame whose stored parameters were
    unreadable was refused ``invalid_input`` with its flags and fields in words only."""
    frame = npy_bytes(np.zeros((8, 8), np.uint8)) if stored is None else png_storing(stored)
    name = "f.npy" if stored is None else "f.png"
    reply = client().post("/v1/reconstructions", files={"file": (name, frame)}, data=given)
    assert reply.status_code == 422, reply.text
    assert reply.json()["parameters"] == asked


def test_truncated_png_is_a_clear_422(client: Client) -> None:
    data, _ = frame_png()
    reply = client().post("/v1/reconstructions", files={"file": ("f.png", data[: len(data) // 2])})
    assert reply.status_code == 422
    assert "truncated" in reply.json()["message"]


@pytest.mark.parametrize(
    ("content", "name", "declared"),
    [
        ("png", "frame.tiff", None),
        ("png", "frame.png", "tiff"),
        ("tiff", "frame.png", None),
        ("npy", "frame.tif", None),
        ("png", "frame.npy", None),
        ("png", "frame.raw", None),
    ],
)
def test_a_frame_is_decoded_by_its_content_whatever_its_name(
    client: Client, content: str, name: str, declared: str | None
) -> None:
    """A PNG named .tiff was refused as a corrupt TIFF ('not a TIFF file')."""
    _, codes = frame_png()
    fields = {**PARAMS.model_dump(exclude_none=True), **({"format": declared} if declared else {})}
    reply = client().post(
        "/v1/reconstructions",
        files={"file": (name, encode_frame(codes, PARAMS, content))},
        data={key: str(value) for key, value in fields.items()},
    )
    assert reply.status_code == 202, reply.text


def test_a_frame_read_by_its_content_tells_the_client(client: Client, worker: Worker) -> None:
    """A PNG named .tiff is read as a PNG, and that was said only in the server's log:
    the job's ``warnings`` say it, in the 202, the 200 of ``Prefer: wait`` and the job's
    state. A frame named as what it is has none."""
    data, _ = frame_png()
    http = client()
    accepted = http.post("/v1/reconstructions", files={"file": ("frame.tiff", data)})
    assert accepted.status_code == 202, accepted.text
    (warning,) = accepted.json()["warnings"]
    assert "content is PNG although its name or declared format says TIFF" in warning
    assert http.get(accepted.json()["url"]).json()["warnings"] == [warning]
    waited = http.post("/v1/reconstructions", files={"file": ("frame.npy", data)},
                       headers={"Prefer": "wait=30"})
    assert waited.status_code == 200 and waited.json()["state"] == "succeeded", waited.text
    assert waited.json()["warnings"] == [warning.replace("TIFF", "NPY")]
    named = http.post("/v1/reconstructions", files={"file": ("frame.png", data)})
    assert named.json()["warnings"] == []
    assert http.get(named.json()["url"]).json()["warnings"] == []


@pytest.mark.parametrize(("name", "declared"), [("frame", "raw"), ("frame.raw", None)])
def test_a_frame_declared_raw_without_a_size_but_a_png_says_so(
    client: Client, name: str, declared: str | None
) -> None:
    """Declared or named raw with no width and height, a PNG was decoded as a PNG with no
    warning, although the README says the name decides only when the bytes show no format."""
    data, _ = frame_png()
    http = client()
    accepted = http.post("/v1/reconstructions", files={"file": (name, data)},
                         data={"format": declared} if declared else {})
    assert accepted.status_code == 202, accepted.text
    (warning,) = accepted.json()["warnings"]
    assert "content is PNG although its name or declared format says RAW" in warning
    assert http.get(accepted.json()["url"]).json()["warnings"] == [warning]


def test_8_bit_codes_sent_as_wider_tell_the_client(client: Client) -> None:
    """Codes all below 256 with bits=16 (an 8-bit frame, or the wrong bits) decode as
    almost black: that was said only in the server's log; the job's ``warnings`` say it."""
    codes = npy_bytes(np.arange(64, dtype=np.uint8).reshape(8, 8))
    http = client()
    accepted = http.post("/v1/reconstructions", files={"file": ("f.npy", codes)},
                         data={"encoding": "modulo", "bits": "16"})  # fmt: skip
    assert accepted.status_code == 202, accepted.text
    (warning,) = accepted.json()["warnings"]
    assert "every code is below 256 although bits is 16" in warning and "bits=8" in warning
    assert http.get(accepted.json()["url"]).json()["warnings"] == [warning]


def test_an_hdr_image_named_as_a_frame_is_pointed_to_simulate(client: Client) -> None:
    """It was 'the data is not a PNG image (bad or missing signature)'."""
    reply = client().post("/v1/reconstructions", files={"file": ("scene.png", exr_bytes())})
    assert reply.status_code == 415, reply.text
    assert "an OpenEXR image" in reply.json()["message"]
    assert "POST /v1/simulate" in reply.json()["message"]


def test_a_zstandard_tiff_frame_is_415_naming_the_compressions_accepted(client: Client) -> None:
    """A Zstandard TIFF (Pillow writes one) was a 422 'truncated or corrupt (No module
    named 'compression')' on Python 3.11."""
    buffer = io.BytesIO()
    Image.fromarray(np.zeros((8, 8), np.uint8)).save(buffer, "TIFF", compression="zstd")
    reply = client().post("/v1/reconstructions", files={"file": ("f.tiff", buffer.getvalue())},
                          data={"encoding": "modulo", "bits": "8"})  # fmt: skip
    assert reply.status_code == 415, reply.text
    assert reply.json()["code"] == "unsupported_format"
    assert "compression ZSTD (50000)" in reply.json()["message"]
    assert "accepted are none, deflate (zlib), PackBits, LZMA" in reply.json()["message"]


def test_a_miniswhite_tiff_frame_is_decoded_from_the_codes_it_stands_for(
    client: Client, worker: Worker
) -> None:
    """A MinIsWhite TIFF frame (the largest value black) was decoded from its samples as
    stored, 255 - code, without a word."""
    _, codes = frame_png()
    http = client()
    data = miniswhite_tiff(255 - codes, PARAMS)
    reply = http.post("/v1/reconstructions", files={"file": ("f.tiff", data)})
    assert reply.status_code == 202, reply.text
    assert finished_job(http, reply.json()["id"])["state"] == "succeeded"
    stored = http.get(f"{reply.json()['url']}/result", params={"part": "codes", "format": "npy"})
    np.testing.assert_array_equal(np.load(io.BytesIO(stored.content)), codes)


def test_a_floating_point_miniswhite_tiff_frame_is_415_naming_minisblack(client: Client) -> None:
    data = miniswhite_tiff(np.ones((8, 8), "f4"), PARAMS)
    reply = client().post("/v1/reconstructions", files={"file": ("f.tiff", data)})
    assert reply.status_code == 415, reply.text
    assert "save the image as grey MinIsBlack" in reply.json()["message"]


def test_a_tiff_frame_with_a_transparency_mask_decodes(client: Client, worker: Worker) -> None:
    """A TIFF frame followed by the 1-bit transparency-mask page some editors write
    (NewSubfileType 4) was a 422 "more than one page of full resolution"."""
    _, codes = frame_png()
    http = client()
    reply = http.post(
        "/v1/reconstructions", files={"file": ("frame.tiff", with_masks(codes, (), (4,)))}
    )
    assert reply.status_code == 202, reply.text
    assert finished_job(http, reply.json()["id"])["state"] == "succeeded"


def test_too_many_pixels_is_413_before_decoding(client: Client) -> None:
    bomb = encode_frame(np.zeros((1024, 1024), np.uint8), PARAMS, "png")
    assert len(bomb) < 20_000  # a small file that would expand to a large image
    reply = client().post("/v1/reconstructions", files={"file": ("bomb.png", bomb)})
    assert reply.status_code == 413
    assert reply.json()["code"] == "image_too_large"


@pytest.mark.parametrize(
    ("fields", "fragment"),
    [
        ({"decoder": "nope"}, "unknown decoder"),
        ({"decoder": "graphcut+puma+colour+puma"}, "repeats +puma"),
        ({"decoder": "itoh", "quality": "fast"}, "not decoder and quality"),
        ({"quality": "fast", "latency_ms": "40"}, "not quality and latency_ms"),
        ({"latency_ms": "0"}, "latency_ms"),
        ({"quality": "ultra"}, "quality"),
        ({"bits": "twelve"}, "bits"),
        ({"alpha": "0.5"}, "alpha"),
        ({"colour": "red"}, "colour"),
        ({"exr_compression": "lzw"}, "exr_compression"),
    ],
)
def test_bad_form_fields(client: Client, fields: dict[str, str], fragment: str) -> None:
    data, _ = frame_png()
    reply = client().post("/v1/reconstructions", files={"file": ("f.png", data)}, data=fields)
    assert reply.status_code == 422, reply.text
    assert reply.json()["code"] in ("invalid_input", "missing_parameter")
    assert fragment in reply.json()["message"]


def test_a_long_decoder_name_is_not_echoed_whole(client: Client) -> None:
    """A 100 KB decoder name made a 101 KB error body."""
    data, _ = frame_png()
    reply = client().post(
        "/v1/reconstructions", files={"file": ("f.png", data)}, data={"decoder": "x" * 100_000}
    )
    assert reply.status_code == 422
    assert len(reply.content) < 2_000 and "(and 99920 more characters)" in reply.text


def test_missing_file_field_and_wrong_content_type(client: Client) -> None:
    reply = client().post("/v1/reconstructions", data={"bits": "8"}, files={"other": ("a", b"x")})
    assert reply.status_code == 422 and "'file'" in reply.json()["message"]
    reply = client().post(
        "/v1/reconstructions", content=b"{}", headers={"Content-Type": "application/json"}
    )
    assert reply.status_code == 415 and reply.json()["code"] == "unsupported_format"


@pytest.mark.parametrize(
    ("data", "route"), [(None, "/v1/simulate"), (b"PK\x03\x04rest", "/v1/videos")]
)
def test_an_hdr_image_or_a_zip_is_pointed_to_its_route(
    client: Client, data: bytes | None, route: str
) -> None:
    """Both got only 'cannot tell the frame's format'."""
    reply = client().post("/v1/reconstructions",
                          files={"file": ("upload", data if data is not None else exr_bytes())})
    assert reply.status_code == 415 and route in reply.json()["message"]


def test_malformed_multipart_bodies_say_how_to_send_one(client: Client) -> None:
    data, _ = frame_png()
    two = client().post(
        "/v1/reconstructions", files=[("file", ("a.png", data)), ("file", ("b.png", data))]
    )
    assert two.status_code == 400 and two.json()["code"] == "bad_request"
    assert "Too many files" in two.json()["message"] and "curl -F" in two.json()["message"]
    whole = httpx.Request("POST", "http://x", files={"file": ("a.png", data)})
    body = whole.read()
    cut = body[: body.rindex(b"--", 0, len(body) - 4)]  # no closing boundary
    reply = client().post(
        "/v1/reconstructions", content=cut,
        headers={"Content-Type": whole.headers["Content-Type"]},
    )  # fmt: skip
    assert reply.status_code == 422 and "cut short" in reply.json()["message"]


def test_read_only_key_cannot_submit(client: Client) -> None:
    data, _ = frame_png()
    reply = client(READ_KEY).post("/v1/reconstructions", files={"file": ("f.png", data)})
    assert reply.status_code == 403 and reply.json()["code"] == "forbidden"


def test_only_so_many_requests_wait_for_their_jobs_at_once(
    tmp_path: Path, redis_url: str
) -> None:
    """A wait holds one of the server's threads: past ``max_waiting_requests`` an
    upload gets its 202 at once (no worker runs, so a waiting one waits it out)."""
    # One decode slot: the waiting upload must not hold it while it waits.
    settings = make_settings(tmp_path, redis_url, max_waiting_requests=1,
                             max_concurrent_decodes=1)
    data, _ = frame_png()

    def upload(url: str, wait_s: int) -> httpx.Response:
        return httpx.post(f"{url}/v1/reconstructions", files={"file": ("f.png", data)},
                          headers={"Authorization": f"Bearer {FULL_KEY}",
                                   "Prefer": f"wait={wait_s}"}, timeout=60)

    app = create_app(settings)
    with serve(app) as url, ThreadPoolExecutor(1) as pool:
        waiting = pool.submit(upload, url, 8)
        deadline = time.monotonic() + 30
        while not app.state.mcam.wait_slots.full:  # its job is queued and it waits for it
            assert not waiting.done(), f"the first upload did not wait: {waiting.result()}"
            assert time.monotonic() < deadline, "the first upload never waited for its job"
            time.sleep(0.05)
        hurried = upload(url, 8)
        assert hurried.status_code == 202 and "preference-applied" not in hurried.headers
        assert not waiting.done(), "the first upload should still be waiting for its job"
        assert waiting.result().status_code == 202


def test_uploads_are_decoded_a_few_at_a_time(tmp_path: Path, redis_url: str) -> None:
    """Nothing bounded the decodes and simulates the API runs in its own memory: six
    4096 x 4096 simulates from one key took the host's (3.6 GB each). Past
    MCAM_MAX_CONCURRENT_DECODES an upload waits MCAM_DECODE_WAIT_S (here 0), then 503;
    a slot is freed however its upload ends."""
    settings = make_settings(tmp_path, redis_url, max_concurrent_decodes=1, decode_wait_s=0)
    app = create_app(settings)
    frame, _ = frame_png()
    video = npy_bytes(np.zeros((3, 16, 16), np.uint8))
    sensor = {"encoding": "mantissa", "alpha": "2", "bits": "8"}
    uploads = {"/v1/simulate": ("s.exr", exr_bytes(), {**sensor, "gain": "1"}),
               "/v1/reconstructions": ("f.png", frame, {}),
               "/v1/videos": ("v.npy", video, {**sensor, "outputs": "exr_zip"})}
    headers = {"Authorization": f"Bearer {FULL_KEY}"}
    with serve(app) as url, httpx.Client(base_url=url, headers=headers, timeout=60) as http:

        def post(path: str, content: bytes | None = None) -> httpx.Response:
            name, data, fields = uploads[path]
            return http.post(path, files={"file": (name, content or data)}, data=fields)

        slots = app.state.mcam.decode_slots
        assert slots.take()  # another upload being decoded
        for path in uploads:
            refused = post(path)
            assert refused.status_code == 503, (path, refused.text)
            assert refused.json()["code"] == "server_busy"
            assert refused.headers["retry-after"] == "5"
            assert "MCAM_MAX_CONCURRENT_DECODES" in refused.json()["message"]
        slots.release()
        for path in uploads:  # refused in the decode: each frees its slot
            assert post(path, b"\x89PNG not a file").status_code in (415, 422), path
        assert [post(path).status_code for path in uploads] == [200, 202, 202]
        assert not slots.full


def test_a_key_with_its_limit_of_jobs_in_the_queue_gets_429_and_other_keys_do_not(
    tmp_path: Path, redis_url: str
) -> None:
    """With no worker running each accepted job stays in the queue and counts against its
    key, a cancelled one too until a worker drops its entry."""
    settings = make_settings(tmp_path, redis_url, max_queued_jobs_per_key=2)
    data, _ = frame_png()
    with serve(create_app(settings)) as url:

        def upload(key: str) -> httpx.Response:
            return httpx.post(f"{url}/v1/reconstructions", files={"file": ("f.png", data)},
                              headers={"Authorization": f"Bearer {key}"}, timeout=60)

        first, second = upload(FULL_KEY), upload(FULL_KEY)
        assert first.status_code == second.status_code == 202
        refused = upload(FULL_KEY)
        assert refused.status_code == 429, refused.text
        assert refused.json()["code"] == "too_many_jobs"
        assert refused.headers["retry-after"] == "5"  # it had none (the viewer waits on it)
        assert "MCAM_MAX_QUEUED_JOBS_PER_KEY" in refused.json()["message"]
        assert upload(SUBMIT_KEY).status_code == 202
        assert connect(redis_url).xlen(JOBS_STREAM) == 3
        cancel = httpx.delete(f"{url}/v1/jobs/{first.json()['id']}",
                              headers={"Authorization": f"Bearer {FULL_KEY}"}, timeout=60)
        assert cancel.status_code == 200, cancel.text
        assert upload(FULL_KEY).status_code == 429
        with running_worker(settings):
            deadline = time.monotonic() + 30
            while connect(redis_url).xlen(JOBS_STREAM) and time.monotonic() < deadline:
                time.sleep(0.05)
        assert upload(FULL_KEY).status_code == 202


@pytest.mark.parametrize(
    ("prefer", "wait_s"),
    [
        (None, 0.0),
        ("wait=5", 5.0),
        ("WAIT = 2.5", 2.5),
        ('wait="7"', 7.0),
        ("respond-async, wait=10", 10.0),
        ("wait=10; foo=bar", 10.0),
        ("wait=100", 60.0),
        ("wait=1e3", 0.0),
        ("wait=5s", 0.0),
        ("nowait=5", 0.0),
    ],
)
def test_the_prefer_header_s_wait_is_read_whole(prefer: str | None, wait_s: float) -> None:
    """``wait=1e3`` was read as 1 s and ``wait=5s`` as 5 s (the leading digits), and a
    quoted ``wait="7"``, which RFC 7240 allows, as none."""
    assert prefer_wait_s(prefer, 60.0) == wait_s


def test_a_clip_frame_is_decoded_by_a_learned_decoder_as_mcam_does(
    client: Client, worker: Worker
) -> None:
    """A clipped sensor never wraps (W = 0 whatever the decoder): mcam reconstruct
    decoded it with mantissanet-small, while the API refused it ("has no model for clip
    frames")."""
    codes = np.arange(64, dtype=np.uint8).reshape(8, 8) * 4
    job = decoded_clip_frame(client, codes, "mantissanet-small")
    assert job["decoder"] == "mantissanet-small", job


def decoded_clip_frame(client: Client, codes: np.ndarray, decoder: str) -> dict[str, Any]:
    """The finished job of 8-bit clip ``codes`` sent as an npy to ``decoder``, checked
    to have succeeded with x = the codes' bin centres (W = 0)."""
    reply = client().post(
        "/v1/reconstructions",
        files={"file": ("f.npy", npy_bytes(codes))},
        data={"encoding": "clip", "bits": "8", "decoder": decoder},
        headers={"Prefer": "wait=60"},
    )
    assert reply.status_code == 200, reply.text
    job = reply.json()
    assert job["state"] == "succeeded", job
    result = client().get(job["links"]["result"])
    np.testing.assert_allclose(read_hdr(result.content).pixels, (codes + 0.5) / 256, rtol=1e-6)
    return job


@pytest.mark.parametrize("shape", [(1, 40), (40, 1), (1, 1)])
def test_a_clip_frame_one_pixel_high_or_wide_is_decoded_with_its_results(
    client: Client, worker: Worker, shape: tuple[int, int]
) -> None:
    """A clipped sensor never wraps: mcam reconstruct decodes a 1 x N clip frame (W = 0),
    while the API refused it ("spatial decoders need at least 2 x 2 pixels")."""
    codes = (np.arange(np.prod(shape), dtype=np.uint8) * 6).reshape(shape)
    job = decoded_clip_frame(client, codes, "auto")
    for part, formats in PART_FORMATS.items():
        for fmt in formats:
            answer = client().get(job["links"]["result"], params={"part": part, "format": fmt})
            assert answer.status_code == 200, (part, fmt, answer.text)
