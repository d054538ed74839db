"""/v1/jobs/{id}: state, results (data files and previews), cancel; against real parts."""

from __future__ import annotations

import io
from collections.abc import Callable, Iterator
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from pathlib import Path

import httpx
import numpy as np
import pytest
import tifffile
from PIL import Image

from models.decoders.registry import get_decoder
from models.formation import SensorParams, encode
from models.frames import decode_frame
from models.hdr_io import read_hdr
from service.api.state import Slots
from service.core.config import Settings
from service.main import create_app
from tests.service.conftest import (
    FULL_KEY,
    PARAMS,
    READ_KEY,
    SUBMIT_KEY,
    frame_png,
    make_settings,
    npy_bytes,
    running_worker,
    serve,
)
from tests.worker.conftest import overflowing_codes
from worker.embedded_redis import connect
from worker.redis_keys import job_key
from worker.result_store import RESULTS_DIR
from worker.runner import Worker

Client = Callable[[str], httpx.Client]


def reconstructed_job(http: httpx.Client, **fields: str) -> dict:
    data, _ = frame_png()
    reply = http.post(
        "/v1/reconstructions",
        files={"file": ("frame.png", data)},
        data={"decoder": "itoh", **fields},
        headers={"Prefer": "wait=30"},
    )
    assert reply.status_code == 200, reply.text
    return reply.json()


def test_results_match_the_in_process_decoder(client: Client, worker: Worker) -> None:
    http = client()
    job = reconstructed_job(http)
    assert http.get(f"/v1/jobs/{job['id']}").json()["state"] == "succeeded"
    _, codes = frame_png()
    expected = get_decoder("itoh").decode(codes, PARAMS)
    exr = http.get(f"/v1/jobs/{job['id']}/result")
    assert exr.status_code == 200 and exr.headers["content-type"] == "image/x-exr"
    x_hat = read_hdr(exr.content).pixels
    np.testing.assert_allclose(x_hat, expected.irradiance, rtol=1e-6)
    winding = http.get(f"/v1/jobs/{job['id']}/result", params={"part": "winding"})
    np.testing.assert_array_equal(np.load(io.BytesIO(winding.content)), expected.winding)


def test_codes_part_gives_back_the_uploaded_codes(client: Client, worker: Worker) -> None:
    http = client()
    job = reconstructed_job(http)
    reply = http.get(f"/v1/jobs/{job['id']}/result", params={"part": "codes", "format": "tiff"})
    assert reply.status_code == 200
    _, codes = frame_png()
    np.testing.assert_array_equal(decode_frame(reply.content, "tiff").codes, codes)


def one_channel_job(http: httpx.Client) -> str:
    """The result URL of a job of :func:`frame_png`'s codes sent as an H x W x 1 npy."""
    _, codes = frame_png()
    reply = http.post(
        "/v1/reconstructions",
        files={"file": ("frame.npy", npy_bytes(codes[:, :, None]))},
        data={"decoder": "itoh", "encoding": "mantissa", "alpha": "2", "bits": "8"},
        headers={"Prefer": "wait=30"},
    )
    assert reply.status_code == 200, reply.text
    return f"/v1/jobs/{reply.json()['id']}/result"


def test_the_tiff_parts_of_an_h_x_w_x_1_frame_are_given(client: Client, worker: Worker) -> None:
    """An npy frame stored H x W x 1: its codes and W map as TIFF were 500s (tifffile
    refused the contiguous layout asked for one sample)."""
    _, codes = frame_png()
    http = client()
    url = one_channel_job(http)
    tiff_codes = http.get(url, params={"part": "codes", "format": "tiff"})
    assert tiff_codes.status_code == 200, tiff_codes.text
    np.testing.assert_array_equal(decode_frame(tiff_codes.content, "tiff").codes, codes)
    tiff_winding = http.get(url, params={"part": "winding", "format": "tiff"})
    assert tiff_winding.status_code == 200, tiff_winding.text
    expected = get_decoder("itoh").decode(codes, PARAMS).winding
    np.testing.assert_array_equal(tifffile.imread(io.BytesIO(tiff_winding.content)), expected)


def test_the_png_previews_of_an_h_x_w_x_1_frame_are_given(client: Client, worker: Worker) -> None:
    """The codes preview of an npy frame stored H x W x 1 (the viewer asks for it for
    every job) was a 500: Pillow makes no image of H x W x 1 samples."""
    _, codes = frame_png()
    http = client()
    url = one_channel_job(http)
    for part in ("codes", "image", "winding"):
        reply = http.get(url, params={"part": part, "format": "png"})
        assert reply.status_code == 200, (part, reply.text)
    preview = np.asarray(Image.open(io.BytesIO(reply.content)))
    assert preview.shape == (*codes.shape, 3)
    grey = np.asarray(Image.open(io.BytesIO(http.get(url, params={"part": "codes"}).content)))
    assert grey.shape == codes.shape


#: 16-bit modulo frames: noise (a few wraps) and a ramp to 1000 wraps, a quarter wrap a step.
CODES_16_BIT = {
    "noise": np.random.default_rng(3).integers(0, 2**16, (16, 16)).astype(np.uint16),
    "ramp": encode(
        np.tile(np.linspace(0.0, 1000.0, 4096), (8, 1)), SensorParams(encoding="modulo", bits=16)
    ).codes,
}


@pytest.mark.parametrize(("frame", "half"), [("noise", "false"), ("noise", "true"),
                                             ("ramp", "false")])
def test_codes_part_gives_back_16_bit_codes_whatever_the_exr_precision(
    client: Client, worker: Worker, frame: str, half: str
) -> None:
    """No EXR carries every frame's 16-bit codes back: re-encoded from a half-float one, 244
    of 256 noise codes were off, by up to 31 DN; from a float32 one (24 bits: W and 16 bits
    of fraction only below 256 wraps), 17056 of 32768 ramp codes, by up to 2 DN. Every job
    keeps the codes themselves."""
    http = client()
    codes = CODES_16_BIT[frame]
    reply = http.post(
        "/v1/reconstructions",
        files={"file": ("frame.npy", npy_bytes(codes))},
        data={"decoder": "itoh", "encoding": "modulo", "bits": "16", "half": half},
        headers={"Prefer": "wait=30"},
    )
    assert reply.status_code == 200, reply.text
    back = http.get(f"/v1/jobs/{reply.json()['id']}/result",
                    params={"part": "codes", "format": "npy"})
    assert back.status_code == 200
    np.testing.assert_array_equal(np.load(io.BytesIO(back.content)), codes)


def test_previews_and_histogram(client: Client, worker: Worker) -> None:
    http = client(READ_KEY)
    job = reconstructed_job(client())
    url = f"/v1/jobs/{job['id']}/result"
    dark = Image.open(io.BytesIO(http.get(url, params={"format": "png", "exposure": -6}).content))
    bright = Image.open(io.BytesIO(http.get(url, params={"format": "png", "exposure": 2}).content))
    assert dark.size == (64, 64) and dark.mode == "L"
    assert np.asarray(dark).mean() < np.asarray(bright).mean()
    w_png = Image.open(
        io.BytesIO(http.get(url, params={"part": "winding", "format": "png"}).content)
    )
    assert w_png.mode == "RGB" and w_png.size == (64, 64)
    histogram = http.get(url, params={"part": "histogram"}).json()
    assert len(histogram["counts"]) == len(histogram["log10_edges"]) - 1
    assert sum(histogram["counts"]) + histogram["zero_pixels"] == 64 * 64


@pytest.mark.parametrize(
    ("params", "status"),
    [
        ({"part": "histogram", "format": "png"}, 422),
        ({"part": "image", "format": "npy"}, 422),
        ({"part": "volume"}, 422),
        ({"exposure": "99"}, 422),
        ({"exposure": "nan", "format": "png"}, 422),
        ({"format": "gif"}, 422),
    ],
)
def test_bad_result_queries(client: Client, worker: Worker, params: dict, status: int) -> None:
    job = reconstructed_job(client())
    reply = client().get(f"/v1/jobs/{job['id']}/result", params=params)
    assert reply.status_code == status, reply.text
    assert reply.json()["code"] == "invalid_input"
    if params.get("exposure") == "nan":  # it said "less than or equal to 30"
        assert "finite number" in reply.text


def test_an_exposure_for_a_file_it_does_not_shape_is_refused(
    client: Client, worker: Worker
) -> None:
    """``?exposure=2`` alone got the EXR, unchanged, as if it had not been given (and so
    did an exposure with the W map, the codes or the histogram): the client meant the
    tonemapped preview, which only ``format=png`` of the image gives."""
    url = f"/v1/jobs/{reconstructed_job(client())['id']}/result"
    for params in (
        {"exposure": "2"},
        {"format": "exr", "exposure": "0"},
        {"part": "winding", "exposure": "-1"},
        {"part": "codes", "format": "png", "exposure": "1"},
        {"part": "histogram", "exposure": "1"},
    ):
        reply = client().get(url, params=params)
        assert reply.status_code == 422, (params, reply.text)
        assert reply.json()["code"] == "invalid_input"
        assert "ask for part=image&format=png with it" in reply.json()["message"]
    assert client().get(url, params={"format": "png", "exposure": "2"}).status_code == 200


def test_queued_job_has_no_result_and_can_be_cancelled(client: Client) -> None:
    data, _ = frame_png()
    job = client(SUBMIT_KEY).post("/v1/reconstructions", files={"file": ("f.png", data)}).json()
    reply = client().get(f"/v1/jobs/{job['id']}/result")
    assert reply.status_code == 409 and reply.json()["code"] == "job_not_finished"
    cancelled = client(SUBMIT_KEY).delete(f"/v1/jobs/{job['id']}")
    assert cancelled.status_code == 200 and cancelled.json()["state"] == "cancelled"
    assert client(SUBMIT_KEY).delete(f"/v1/jobs/{job['id']}").status_code == 200
    assert client(READ_KEY).delete(f"/v1/jobs/{job['id']}").status_code == 403
    gone = client().get(f"/v1/jobs/{job['id']}/result")
    assert gone.status_code == 409 and gone.json()["code"] == "job_cancelled"
    assert "cancelled" in gone.json()["message"]


def test_an_unfinished_video_job_says_where_its_files_will_come_from(client: Client) -> None:
    """A video job's files never come from /v1/jobs/{id}/result: while it is not finished
    the answer says where they will come from and which it will make (it said only to poll
    until it succeeded, and then answered 409 ``video_job``)."""
    clip = npy_bytes(np.zeros((2, 64, 64), np.uint8))
    job = client(SUBMIT_KEY).post(
        "/v1/videos", files={"file": ("clip.npy", clip)},
        data={"encoding": "modulo", "bits": "8", "outputs": "exr_zip,hdr10"},
    ).json()
    reply = client().get(f"/v1/jobs/{job['id']}/result")
    assert reply.status_code == 409 and reply.json()["code"] == "job_not_finished"
    message = reply.json()["message"]
    assert message.startswith(f"job {job['id']} is queued")
    assert message.endswith(
        f"/v1/videos/{job['id']}/result?output=exr_zip (it will make exr_zip, hdr10)"
    ), message


def test_finished_job_cannot_be_cancelled(client: Client, worker: Worker) -> None:
    job = reconstructed_job(client())
    reply = client().delete(f"/v1/jobs/{job['id']}")
    assert reply.status_code == 409 and reply.json()["code"] == "job_finished"


@pytest.mark.parametrize("job_id", ["0" * 32, "..%2F..%2Fetc%2Fpasswd", "ABC", "0" * 31 + "g"])
def test_unknown_or_malformed_ids_are_404(client: Client, job_id: str) -> None:
    for path in (f"/v1/jobs/{job_id}", f"/v1/jobs/{job_id}/result"):
        reply = client().get(path)
        assert reply.status_code == 404, path
        assert reply.json()["code"] == "not_found"


def test_an_expired_job_says_to_submit_it_again(
    client: Client, worker: Worker, settings: Settings
) -> None:
    """A job whose record expired after retention answered 'not_found: no job ...
    (unknown, or expired after retention)' for its state, result and previews, without
    saying what to do."""
    http = client()
    job = reconstructed_job(http)
    assert settings.redis_url is not None
    connect(settings.redis_url, timeout_s=5.0).delete(job_key(job["id"]))
    for path, params in ((f"/v1/jobs/{job['id']}", {}), (f"/v1/jobs/{job['id']}/result", {}),
                         (f"/v1/jobs/{job['id']}/result", {"part": "image", "format": "png"})):
        reply = http.get(path, params=params)
        assert reply.status_code == 404 and reply.json()["code"] == "not_found", path
        message = reply.json()["message"]
        assert "MCAM_RESULT_RETENTION_S" in message and "submit the job again" in message


def test_submit_only_key_cannot_read(client: Client) -> None:
    reply = client(SUBMIT_KEY).get(f"/v1/jobs/{'0' * 32}")
    assert reply.status_code == 403


def test_a_failed_job_says_no_result_will_come(client: Client, worker: Worker) -> None:
    buffer = io.BytesIO()
    np.save(buffer, overflowing_codes())
    reply = client().post(
        "/v1/reconstructions",
        files={"file": ("overflow.npy", buffer.getvalue())},
        data={"decoder": "itoh", "encoding": "mantissa", "alpha": "1e6", "bits": "8"},
        headers={"Prefer": "wait=30"},
    )
    assert reply.json()["state"] == "failed", reply.text
    result = client().get(f"/v1/jobs/{reply.json()['id']}/result")
    assert result.status_code == 409 and result.json()["code"] == "job_failed"
    assert "no result" in result.json()["message"]


def test_expired_result_files_are_404_for_every_part(
    client: Client, worker: Worker, settings: Settings
) -> None:
    """Retention removes files before their job record: each part then says so (the
    W map answered 500)."""
    http = client()
    job = reconstructed_job(http)
    for path in (settings.data_dir / RESULTS_DIR).rglob("*"):
        if path.is_file():
            path.unlink()
    for params in ({}, {"part": "winding"}, {"part": "winding", "format": "png"},
                   {"part": "image", "format": "png"}, {"part": "codes"}, {"part": "histogram"}):
        reply = http.get(f"/v1/jobs/{job['id']}/result", params=params)
        assert reply.status_code == 404, (params, reply.text)
        assert "never written or expired" in reply.json()["message"]


def test_stored_results_support_range_head_and_caching(client: Client, worker: Worker) -> None:
    """A player seeks and a broken download resumes (Range); a link checker asks HEAD;
    a job's result never changes, so it is cached for good."""
    http = client()
    job = reconstructed_job(http)
    url = f"/v1/jobs/{job['id']}/result"
    whole = http.get(url)
    assert whole.status_code == 200 and "immutable" in whole.headers["cache-control"]
    assert whole.headers["etag"] and whole.headers["last-modified"]
    part = http.get(url, headers={"Range": "bytes=10-99"})
    assert part.status_code == 206 and part.content == whole.content[10:100]
    assert part.headers["content-range"] == f"bytes 10-99/{len(whole.content)}"
    head = http.head(url)
    assert head.status_code == 200 and head.content == b""
    assert int(head.headers["content-length"]) == len(whole.content)
    assert http.head(f"/v1/jobs/{'0' * 32}").status_code == 404
    for path in ("/health/live", "/v1/decoders", "/"):
        assert http.head(path).status_code == 200, path


#: The result parts read whole into the API's memory to answer (all but the stored EXR).
IN_MEMORY_PARTS = (
    {"format": "png"},
    {"part": "winding"},
    {"part": "winding", "format": "png"},
    {"part": "codes"},
    {"part": "codes", "format": "tiff"},
    {"part": "histogram"},
)


@contextmanager
def one_decode_slot(
    tmp_path: Path, redis_url: str, wait_s: float
) -> Iterator[tuple[httpx.Client, str, Slots]]:
    """A live API with one decode slot (waited for ``wait_s`` s) and a worker: an HTTP
    client, the result URL of a succeeded job, and the slots."""
    settings = make_settings(tmp_path, redis_url, max_concurrent_decodes=1, decode_wait_s=wait_s)
    app = create_app(settings)
    headers = {"Authorization": f"Bearer {FULL_KEY}"}
    with (
        serve(app) as url,
        running_worker(settings),
        httpx.Client(base_url=url, headers=headers, timeout=60) as http,
    ):
        job = reconstructed_job(http)
        yield http, f"/v1/jobs/{job['id']}/result", app.state.mcam.decode_slots


def test_previews_are_made_a_few_at_a_time(tmp_path: Path, redis_url: str) -> None:
    """A preview, W map, codes or histogram reads the whole result and works on it in
    the API's memory, and nothing bounded how many ran at once (a viewer asks for four
    per job). They share the uploads' MCAM_MAX_CONCURRENT_DECODES: past it one waits
    MCAM_DECODE_WAIT_S (here 0), then 503 server_busy with Retry-After; the stored EXR is
    streamed from disk and needs no slot."""
    with one_decode_slot(tmp_path, redis_url, 0) as (http, result, slots):
        assert slots.take()  # an upload being decoded
        for params in IN_MEMORY_PARTS:
            refused = http.get(result, params=params)
            assert refused.status_code == 503, (params, refused.text)
            assert refused.json()["code"] == "server_busy"
            assert refused.headers["retry-after"] == "5"
            assert "MCAM_MAX_CONCURRENT_DECODES" in refused.json()["message"]
        assert http.get(result).status_code == 200  # the EXR: streamed, no slot
        slots.release()
        for params in IN_MEMORY_PARTS:
            assert http.get(result, params=params).status_code == 200, params
        assert http.get(result, params={"part": "codes", "format": "gif"}).status_code == 422
        assert not slots.full


def test_a_preview_waits_its_turn(tmp_path: Path, redis_url: str) -> None:
    """Within MCAM_DECODE_WAIT_S a preview waits for a slot (on the event loop) and is
    answered once one is freed; it is not refused."""
    with (
        one_decode_slot(tmp_path, redis_url, 60) as (http, result, slots),
        ThreadPoolExecutor(1) as pool,
    ):
        assert slots.take()
        waiting = pool.submit(http.get, result, params={"part": "histogram"})
        assert http.get(result.removesuffix("/result")).status_code == 200
        assert not waiting.done(), "the preview did not wait for the held slot"
        slots.release()
        assert waiting.result().status_code == 200
        assert not slots.full
