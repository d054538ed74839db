"""POST /v1/videos against a live API, a real Redis and a real worker, files read back."""

from __future__ import annotations

import io
import zipfile
from collections.abc import Callable
from pathlib import Path

import av
import httpx
import numpy as np
import OpenEXR
import tifffile

from models.formation import SensorParams, encode
from models.frames import encode_frame
from models.hdr_io import read_hdr
from service.main import create_app
from tests.service.conftest import FULL_KEY, finished_job, make_settings, npy_bytes, serve
from worker.embedded_redis import connect
from worker.redis_keys import JOBS_STREAM
from worker.runner import Worker

Client = Callable[[str], httpx.Client]
FRAMES, SIZE = 30, 64
PARAMS = SensorParams(encoding="mantissa", alpha=2.0, bits=8)
FLAGS = {"encoding": "mantissa", "alpha": "2", "bits": "8"}


def slow_clip() -> list[np.ndarray]:
    """A smooth blob (x up to ~9 wraps) brightening 2% per frame."""
    yy, xx = np.mgrid[0:SIZE, 0:SIZE] - SIZE / 2
    base = 0.05 + 8.0 * np.exp(-(yy**2 + xx**2) / 20.0**2)
    return [base * 1.02**t for t in range(FRAMES)]


def test_thirty_frame_video_end_to_end(client: Client, worker: Worker) -> None:
    truth = slow_clip()
    codes = np.stack([encode(x, PARAMS).codes for x in truth])
    http = client()
    reply = http.post(
        "/v1/videos",
        files={"file": ("clip.npy", npy_bytes(codes))},
        data={**FLAGS, "mode": "temporal", "decoder": "itoh"},
    )
    assert reply.status_code == 202, reply.text
    job = finished_job(http, reply.json()["id"])
    assert job["state"] == "succeeded", job
    assert job["kind"] == "video"
    assert job["frames_done"] == job["frames_total"] == FRAMES and job["progress"] == 1.0
    assert job["info"]["keyframes"] == 1 and job["info"]["paths"]["temporal"] > 0.9
    hdr10 = http.get(f"/v1/videos/{job['id']}/result", params={"output": "hdr10"})
    assert hdr10.status_code == 200 and hdr10.headers["content-type"] == "video/mp4"
    with av.open(io.BytesIO(hdr10.content)) as container:
        stream = container.streams.video[0]
        assert stream.codec_context.name == "hevc"
        assert stream.codec_context.pix_fmt == "yuv420p10le"
        assert sum(1 for _ in container.decode(stream)) == FRAMES
    sdr = http.get(f"/v1/videos/{job['id']}/result", params={"output": "sdr"})
    with av.open(io.BytesIO(sdr.content)) as container:
        assert container.streams.video[0].codec_context.name == "h264"
    exr = http.get(f"/v1/videos/{job['id']}/result", params={"output": "exr_zip"})
    with zipfile.ZipFile(io.BytesIO(exr.content)) as archive:
        names = archive.namelist()
        assert len(names) == FRAMES
        for name, x in zip(names, truth, strict=True):
            pixels = read_hdr(archive.read(name)).pixels
            half_bin = 2.0**-9
            bound = np.where(x < 1, half_bin, x * (2.0**half_bin - 1)) + 1e-6 * x
            assert np.all(np.abs(pixels - x) <= bound), name


def test_zip_of_pngs_independent_exr_only(client: Client, worker: Worker) -> None:
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w") as archive:
        for t, x in enumerate(slow_clip()[:4]):
            archive.writestr(f"f{t}.png", encode_frame(encode(x, PARAMS).codes, PARAMS, "png"))
    http = client()
    reply = http.post(
        "/v1/videos",
        content=buffer.getvalue(),
        params={"mode": "independent", "outputs": "exr_zip,exr_zip", "exr_compression": "none"},
        headers={"Content-Type": "application/octet-stream"},
    )
    assert reply.status_code == 202, reply.text
    job = finished_job(http, reply.json()["id"])
    assert job["state"] == "succeeded" and set(job["results"]) == {"exr_zip"}
    assert job["options"]["outputs"] == ["exr_zip"]
    files = f"/v1/videos/{job['id']}/result?output=exr_zip"  # it linked /v1/jobs/.../result
    assert job["links"] == {"self": f"/v1/jobs/{job['id']}", "result": files,
                            "result_exr_zip": files}
    frames = http.get(job["links"]["result"])
    with zipfile.ZipFile(io.BytesIO(frames.content)) as archive:
        headers = [
            OpenEXR.File(io.BytesIO(archive.read(name)), header_only=True).header()
            for name in archive.namelist()
        ]
    assert [h["compression"] for h in headers] == [OpenEXR.NO_COMPRESSION] * 4
    missing = http.get(f"/v1/videos/{job['id']}/result", params={"output": "hdr10"})
    assert missing.status_code == 409 and missing.json()["code"] == "output_not_made"
    assert "exr_zip" in missing.json()["message"]
    still = http.get(f"/v1/jobs/{job['id']}/result")
    assert still.status_code == 409 and still.json()["code"] == "video_job"
    # only what the job made: it suggested ?output=hdr10, sdr or exr_zip to every video
    assert still.json()["message"].endswith(f"{files} (it made exr_zip)")


def test_a_still_job_has_no_video_files(client: Client, worker: Worker) -> None:
    http = client()
    codes = encode(slow_clip()[0], PARAMS).codes
    reply = http.post(
        "/v1/reconstructions", files={"file": ("f.npy", npy_bytes(codes))}, data=FLAGS
    )
    assert reply.status_code == 202, reply.text
    job = finished_job(http, reply.json()["id"])
    assert job["state"] == "succeeded", job
    wrong = http.get(f"/v1/videos/{job['id']}/result")
    assert wrong.status_code == 409 and wrong.json()["code"] == "not_a_video_job"
    assert f"/v1/jobs/{job['id']}/result" in wrong.json()["message"]


def test_bad_uploads_are_refused(client: Client) -> None:
    http = client()
    small = npy_bytes(np.zeros((3, 16, 16), np.uint8))
    pages = io.BytesIO()
    tifffile.imwrite(pages, np.zeros((12, 16, 16), np.uint8), metadata=None)
    truncated = pages.getvalue()[: len(pages.getvalue()) // 2]
    cases = [
        ({"file": ("a.tiff", truncated)}, {**FLAGS}, 422, "TIFF video is truncated or corrupt"),
        ({"file": ("a.npy", small)}, {**FLAGS}, 422, "64 x 64"),
        ({"file": ("a.npy", small)}, {**FLAGS, "outputs": "gif"}, 422, "gif"),
        ({"file": ("a.npy", small)}, {**FLAGS, "exr_compression": "lzw"}, 422, "exr_compression"),
        ({"file": ("a.bin", b"hello")}, {**FLAGS}, 415, "format"),
        (
            {"file": ("f.png", encode_frame(np.zeros((16, 16), np.uint8), PARAMS, "png"))},
            {**FLAGS}, 415, "this file is a PNG image, one wrapped frame, not a video",
        ),
        ({"file": ("a.npy", small)}, {"outputs": "exr_zip"}, 422, "--encoding"),
        ({"file": ("a.npy", small)}, {**FLAGS, "fps": "nan"}, 422, "fps: Input should be a finite"),
        (
            {"file": ("a.npy", small)}, {**FLAGS, "white_level": "inf"}, 422,
            "white_level: Input should be a finite",
        ),
        (
            {"file": ("a.npy", small)}, {**FLAGS, "keyframe_interval": str(10**30)}, 422,
            "keyframe_interval: Input should be less than or equal to 33554432",
        ),
        (
            {"file": ("a.npy", npy_bytes(np.zeros((2, 2, 16386), np.uint8)))},
            {**FLAGS, "outputs": "sdr,exr_zip"}, 422,
            "takes frames of at most 16384 pixels a side, got 2 x 16386; ask for outputs=exr_zip",
        ),
    ]
    for files, data, status, fragment in cases:
        reply = http.post("/v1/videos", files=files, data=data)
        assert reply.status_code == status, reply.text
        assert fragment in reply.text


def test_uploads_that_inflate_past_the_limits_are_refused_unread(client: Client) -> None:
    """A few KB that would decode to more than the service takes: 413 naming the limit."""
    pages = io.BytesIO()
    tifffile.imwrite(pages, np.zeros((40, 256, 256), np.uint8), compression="zlib")
    bomb = io.BytesIO()
    with zipfile.ZipFile(bomb, "w", compression=zipfile.ZIP_DEFLATED) as archive:
        archive.writestr("frame_0.png", bytes(64 * 2**20))
    http = client()
    for name, data, fragment in [
        ("clip.tiff", pages.getvalue(), "2621440 code values (40 x 256 x 256)"),
        ("clip.zip", bomb.getvalue(), "frame_0.png inflates to 67108864 bytes"),
    ]:
        assert len(data) < 200_000
        reply = http.post("/v1/videos", files={"file": (name, data)}, data=FLAGS)
        assert reply.status_code == 413, reply.text
        assert reply.json()["code"] == "image_too_large" and fragment in reply.json()["message"]


def test_a_video_counts_against_its_keys_unfinished_jobs(tmp_path: Path, redis_url: str) -> None:
    settings = make_settings(tmp_path, redis_url, max_queued_jobs_per_key=1)
    clip = np.stack([encode(frame, PARAMS).codes for frame in slow_clip()[:3]])
    with serve(create_app(settings)) as url:
        http = httpx.Client(base_url=url, headers={"Authorization": f"Bearer {FULL_KEY}"})
        for expected in (202, 429):
            reply = http.post("/v1/videos", files={"file": ("c.npy", npy_bytes(clip))}, data=FLAGS)
            assert reply.status_code == expected, reply.text
        assert reply.json()["code"] == "too_many_jobs"
        http.close()


def test_an_output_a_queued_video_job_will_not_make_is_refused_at_once(client: Client) -> None:
    """It answered job_not_finished ("poll its state until it succeeded"), and only once
    the job had finished that the job never makes it."""
    codes = np.stack([encode(x, PARAMS).codes for x in slow_clip()[:2]])
    http = client()
    reply = http.post("/v1/videos", files={"file": ("clip.npy", npy_bytes(codes))},
                      data={**FLAGS, "outputs": "exr_zip"})
    assert reply.status_code == 202, reply.text
    files = f"/v1/videos/{reply.json()['id']}/result"
    never = http.get(files, params={"output": "hdr10"})
    assert never.status_code == 409 and never.json()["code"] == "output_not_made"
    assert "will not make 'hdr10'; it makes: exr_zip" in never.json()["message"]
    later = http.get(files, params={"output": "exr_zip"})
    assert later.status_code == 409 and later.json()["code"] == "job_not_finished"


def test_a_queued_still_job_is_not_a_video_at_once(client: Client) -> None:
    """It answered job_not_finished ("poll its state until it succeeded"), and only once
    the job had succeeded that it has no video files."""
    http = client()
    codes = encode(slow_clip()[0], PARAMS).codes
    reply = http.post(
        "/v1/reconstructions", files={"file": ("f.npy", npy_bytes(codes))}, data=FLAGS
    )
    assert reply.status_code == 202, reply.text
    wrong = http.get(f"/v1/videos/{reply.json()['id']}/result")
    assert wrong.status_code == 409 and wrong.json()["code"] == "not_a_video_job"


def test_a_video_is_decoded_by_its_content_whatever_its_name(client: Client) -> None:
    """A zip of PNG frames named .tiff was refused as a corrupt TIFF; it is read as the
    zip it is, and the job's ``warnings`` say so."""
    codes = np.stack([encode(x, PARAMS).codes for x in slow_clip()[:3]])
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w") as archive:
        for t, frame in enumerate(codes):
            archive.writestr(f"frame_{t}.png", encode_frame(frame, PARAMS, "png"))
    reply = client().post("/v1/videos", files={"file": ("clip.tiff", buffer.getvalue())})
    assert reply.status_code == 202, reply.text
    (warning,) = reply.json()["warnings"]  # it was said only in the server's log
    assert "content is ZIP although its name or declared format says TIFF" in warning


def test_8_bit_codes_sent_as_wider_tell_the_client(client: Client) -> None:
    """A clip of codes all below 256 with bits=12 (an npy) or 16 (a zip of 16-bit PNGs):
    the warning was only in the server's log; the job's ``warnings`` say it, once."""
    codes = np.stack([encode(x, PARAMS).codes for x in slow_clip()[:3]])
    http = client()
    reply = http.post("/v1/videos", files={"file": ("clip.npy", npy_bytes(codes))},
                      data={**FLAGS, "bits": "12"})  # fmt: skip
    assert reply.status_code == 202, reply.text
    (warning,) = reply.json()["warnings"]
    assert "every code is below 256 although bits is 12" in warning
    wide = PARAMS.model_copy(update={"bits": 16})
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w") as archive:
        for t, frame in enumerate(codes.astype(np.uint16)):
            archive.writestr(f"frame_{t}.png", encode_frame(frame, wide, "png"))
    reply = http.post("/v1/videos", files={"file": ("clip.zip", buffer.getvalue())})
    assert reply.status_code == 202, reply.text
    assert reply.json()["warnings"] == [warning.replace("bits is 12", "bits is 16")]


def test_mp4_videos_padded_to_even_sides_tell_the_client(client: Client) -> None:
    """4:2:0 video needs even sides: frames of 65 x 67 px give MP4 videos of 66 x 68.
    ``mcam video`` said so; a job said nothing, and its videos were a pixel larger than
    its frames and EXR frames. Its ``warnings`` now say it, unless it makes no MP4."""
    codes = np.zeros((2, 65, 67), np.uint8)
    http = client()
    warnings = [
        http.post(
            "/v1/videos", files={"file": ("clip.npy", npy_bytes(codes))},
            data={**FLAGS, "outputs": outputs},
        ).json()["warnings"]
        for outputs in ("sdr,exr_zip", "exr_zip")
    ]  # fmt: skip
    assert warnings == [
        [
            "the MP4 videos are 66 x 68: 4:2:0 video needs even sides, so the last row / "
            "column of the 65 x 67 frames is repeated (EXR frames keep their size)"
        ],
        [],
    ]


def post_half_floats_at_gain_1e_minus_300(client: Client, outputs: str) -> httpx.Response:
    """POST two frames of :func:`slow_clip` for ``outputs`` as half floats at gain 1e-300."""
    codes = np.stack([encode(x, PARAMS).codes for x in slow_clip()[:2]])
    return client().post(
        "/v1/videos",
        files={"file": ("clip.npy", npy_bytes(codes))},
        data={**FLAGS, "gain": "1e-300", "half": "true", "outputs": outputs},
    )


def test_half_floats_at_a_gain_float32_cannot_take_are_refused_at_submit(
    client: Client, redis_url: str
) -> None:
    """At gain 1e-300 every x / gain exceeds float32 too: POST /v1/reconstructions refused
    it with a 422, while POST /v1/videos queued a job that the worker failed with
    output_overflow after decoding every frame. It is now refused at once, by the same
    check (:func:`worker.outputs.check_result_storable`), naming the frame, and says that
    float32 cannot hold the values either."""
    reply = post_half_floats_at_gain_1e_minus_300(client, "exr_zip")
    assert reply.status_code == 422, reply.text
    assert reply.json()["code"] == "output_overflow", reply.text
    message = reply.json()["message"]
    assert message.startswith("video frame 0: whatever winding numbers a decoder finds")
    assert "float32 output cannot hold them either" in message, message
    assert "instead of half floats" not in message and "a higher gain" in message
    assert connect(redis_url).xlen(JOBS_STREAM) == 0


def test_a_video_without_exr_frames_is_not_refused_for_them(client: Client) -> None:
    """Half floats matter only to the EXR frames: a video of HDR10 alone at gain 1e-300
    is queued."""
    reply = post_half_floats_at_gain_1e_minus_300(client, "hdr10")
    assert reply.status_code == 202, reply.text
