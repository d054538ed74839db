"""POST /v1/simulate over real HTTP: EXR in, wrapped frame (or W) out, every bad input."""

from __future__ import annotations

import io
import json
from collections.abc import Callable

import httpx
import numpy as np
import OpenEXR
import pytest
import tifffile

from models.formation import SensorParams, simulate
from models.frames import decode_frame
from models.hdr_io import encode_exr
from tests.service.conftest import READ_KEY, exr_bytes, scene

Client = Callable[[str], httpx.Client]
FIELDS = {"encoding": "mantissa", "alpha": "2", "bits": "12", "gain": "1"}


def expected_frame(bits: int = 12):
    return simulate(scene(), SensorParams(encoding="mantissa", alpha=2.0, bits=bits, gain=1.0))


def test_exr_to_png_frame_with_params(client: Client) -> None:
    reply = client().post("/v1/simulate", files={"file": ("s.exr", exr_bytes())}, data=FIELDS)
    assert reply.status_code == 200, reply.text
    assert reply.headers["content-type"] == "image/png"
    frame = decode_frame(reply.content, "png")
    np.testing.assert_array_equal(frame.codes, expected_frame().codes)
    assert frame.params.bits == 12 and frame.params.gain == 1.0
    assert json.loads(reply.headers["X-Mcam-Params"])["alpha"] == 2.0


@pytest.mark.parametrize("fmt", ["npy", "tiff"])
def test_other_formats_and_winding(client: Client, fmt: str) -> None:
    http = client()
    files = {"file": ("s.exr", exr_bytes())}
    frame = http.post("/v1/simulate", files=files, data={**FIELDS, "format": fmt})
    assert frame.status_code == 200
    winding = http.post(
        "/v1/simulate", files=files, data={**FIELDS, "format": fmt, "part": "winding"}
    )
    read = np.load if fmt == "npy" else tifffile.imread
    np.testing.assert_array_equal(read(io.BytesIO(frame.content)), expected_frame().codes)
    np.testing.assert_array_equal(read(io.BytesIO(winding.content)), expected_frame().winding)


def test_raw_exr_body_with_query_parameters(client: Client) -> None:
    reply = client().post(
        "/v1/simulate",
        content=exr_bytes(),
        params={**FIELDS, "bits": 8, "format": "npy"},
        headers={"Content-Type": "application/octet-stream"},
    )
    assert reply.status_code == 200, reply.text
    np.testing.assert_array_equal(np.load(io.BytesIO(reply.content)), expected_frame(8).codes)


def test_overexposed_sets_the_gain(client: Client) -> None:
    reply = client().post(
        "/v1/simulate",
        files={"file": ("s.exr", exr_bytes())},
        data={"encoding": "modulo", "bits": "8", "overexposed": "0.25"},
    )
    assert reply.status_code == 200, reply.text
    assert json.loads(reply.headers["X-Mcam-Params"])["gain"] > 0


@pytest.mark.parametrize(
    ("overexposed", "fragments"),
    [
        ("1.0", ("strictly between 0 and 1", "got 1:")),
        ("1.5", ("strictly between 0 and 1", "for 1.5%, give 0.015")),
        ("0.999", ("82 of 4096 pixels (2%) have zero luminance", "at most 0.979")),
    ],
)
def test_overexposed_near_or_above_1_is_explained(
    client: Client, overexposed: str, fragments: tuple[str, ...]
) -> None:
    values = scene()
    values.flat[::50] = 0.0  # 82 of 4096 pixels black: 2%
    reply = client().post(
        "/v1/simulate",
        files={"file": ("s.exr", encode_exr(values))},
        data={"encoding": "modulo", "bits": "8", "overexposed": overexposed},
    )
    assert reply.status_code == 422, reply.text
    assert all(fragment in reply.json()["message"] for fragment in fragments)


def nan_exr() -> bytes:
    values = scene()
    values[3, 3] = np.nan
    buffer = io.BytesIO()
    OpenEXR.File({"type": OpenEXR.scanlineimage}, {"Y": values.astype(np.float32)}).write(buffer)
    return buffer.getvalue()


@pytest.mark.parametrize(
    ("data", "fields", "status", "code"),
    [
        (b"GIF89a not an hdr", FIELDS, 415, "unsupported_format"),
        (exr_bytes()[:200], FIELDS, 422, "invalid_input"),
        (exr_bytes(), {**FIELDS, "overexposed": "0.1"}, 422, "invalid_input"),
        (exr_bytes(), {**FIELDS, "bits": "17"}, 422, "invalid_input"),
        (exr_bytes(), {**FIELDS, "seed": "-1"}, 422, "invalid_input"),
        (exr_bytes(), {**FIELDS, "format": "jpeg"}, 422, "invalid_input"),
        (encode_exr(np.ones((600, 600))), FIELDS, 413, "image_too_large"),
        (encode_exr(np.ones((2, 2)), {f"m{i}": "" for i in range(600)}), FIELDS, 413,
         "image_too_large"),  # fmt: skip
        (encode_exr(-scene()), FIELDS, 422, "negative_irradiance"),
    ],
)
def test_bad_inputs(client: Client, data: bytes, fields: dict, status: int, code: str) -> None:
    reply = client().post("/v1/simulate", files={"file": ("s.exr", data)}, data=fields)
    assert reply.status_code == status, reply.text
    assert reply.json()["code"] == code
    assert reply.json()["message"]


@pytest.mark.parametrize(
    ("field", "value", "fragment"),
    [
        ("max_wraps", "1e-300", "max_wraps: must be at least 1 wrap"),
        ("full_well", "1e-300", "full_well: must be at least 1 electron"),
        ("gain", "1e-300", "every pixel quantises to code 0"),
    ],
)
def test_an_exposure_that_leaves_every_code_0_is_refused_not_returned(
    client: Client, field: str, value: str, fragment: str
) -> None:
    """Each of these at 1e-300 answered 200 with a frame of zeros."""
    reply = client().post(
        "/v1/simulate", files={"file": ("s.exr", exr_bytes())}, data={**FIELDS, field: value}
    )
    assert reply.status_code == 422, reply.text
    assert fragment in reply.json()["message"]


def test_nan_pixels_are_refused(client: Client) -> None:
    reply = client().post("/v1/simulate", files={"file": ("s.exr", nan_exr())}, data=FIELDS)
    assert reply.status_code == 422 and "NaN" in reply.json()["message"]


def test_clip_negative_allows_negative_pixels_and_counts_them(client: Client) -> None:
    """mcam simulate printed how many negative values it clipped; the API did not say."""
    values = np.repeat(scene()[:, :, None], 3, axis=2)
    values[0, 0] = -1.0  # three samples of one pixel
    values[5, 7, 1] = -1e-3
    files = {"file": ("s.exr", encode_exr(values))}
    refused = client().post("/v1/simulate", files=files, data=FIELDS)
    assert refused.status_code == 422  # its own code: the viewer offers the clipping
    assert refused.json()["code"] == "negative_irradiance" and "4 negative" in refused.text
    data = {**FIELDS, "clip_negative": "true"}
    reply = client().post("/v1/simulate", files=files, data=data)
    assert reply.status_code == 200, reply.text
    assert reply.headers["X-Mcam-Clipped-Negative"] == "4"
    clean = client().post("/v1/simulate", files={"file": ("s.exr", exr_bytes())}, data=data)
    assert clean.headers["X-Mcam-Clipped-Negative"] == "0"
    documented = client().get("/openapi.json").json()["paths"]["/v1/simulate"]["post"]
    assert "X-Mcam-Clipped-Negative" in documented["responses"]["200"]["headers"]


def test_needs_the_submit_scope(client: Client) -> None:
    reply = client(READ_KEY).post("/v1/simulate", files={"file": ("s.exr", exr_bytes())})
    assert reply.status_code == 403


def test_colour_scene_as_png_names_the_http_fields(client: Client) -> None:
    """By default a colour scene comes back as TIFF (the default PNG refused every colour
    scene); asked for PNG, the refusal names the fields to change."""
    colour = np.repeat(scene()[:, :, None], 3, axis=2)
    files = {"file": ("s.exr", encode_exr(colour))}
    default = client().post("/v1/simulate", files=files, data=FIELDS)
    assert default.status_code == 200 and default.headers["content-type"] == "image/tiff"
    assert decode_frame(default.content, "tiff").codes.shape == (64, 64, 3)
    reply = client().post("/v1/simulate", files=files, data={**FIELDS, "format": "png"})
    assert reply.status_code == 422 and reply.json()["code"] == "format_cannot_hold_result"
    assert "format=tiff" in reply.json()["message"] and "gray=true" in reply.json()["message"]
    gray = client().post("/v1/simulate", files=files, data={**FIELDS, "gray": "true"})
    assert gray.status_code == 200
    assert decode_frame(gray.content, "png").codes.shape == (64, 64)


@pytest.mark.parametrize(
    ("colour", "fields", "says"),
    [
        (False, {"format": "tiff", "gain": "10000"}, ["TIFF W map", "format=npy"]),
        (False, {"format": "png", "gain": "10000"}, ["PNG W map", "format=npy"]),
        (True, {"format": "png"}, ["PNG W map is grayscale", "format=tiff", "format=npy"]),
    ],
    ids=["W over 65535 as TIFF", "W over 65535 as PNG", "colour W as PNG"],
)
def test_a_result_format_that_cannot_hold_it_is_a_422(
    client: Client, colour: bool, fields: dict[str, str], says: list[str]
) -> None:
    """An output format the result cannot be written in was a 415 unsupported_format,
    which names an upload's format; the request is well-formed and asks for what this
    result cannot give. The message names the formats that can, which give the map."""
    pixels = np.repeat(scene()[:, :, None], 3, axis=2) if colour else scene()
    files = {"file": ("s.exr", encode_exr(pixels))}
    asked = {**FIELDS, "encoding": "modulo", "part": "winding", **fields}
    reply = client().post("/v1/simulate", files=files, data=asked)
    assert reply.status_code == 422, reply.text
    assert reply.json()["code"] == "format_cannot_hold_result"
    assert all(text in reply.json()["message"] for text in says), reply.json()["message"]
    npy = client().post("/v1/simulate", files=files, data={**asked, "format": "npy"})
    assert npy.status_code == 200, npy.text


def test_the_openapi_document_lists_the_422_of_a_format_that_cannot_hold_it(
    client: Client,
) -> None:
    paths = client().get("/openapi.json").json()["paths"]
    for path, method in (("/v1/simulate", "post"), ("/v1/jobs/{job_id}/result", "get")):
        described = paths[path][method]["responses"]["422"]["description"]
        assert "format_cannot_hold_result" in described, path


def test_noise_is_seeded_by_default_as_in_mcam_simulate(client: Client) -> None:
    """The seed was None: the same request gave other noise every time."""
    noisy = {**FIELDS, "read_noise": "0.02"}
    replies = [client().post("/v1/simulate", files={"file": ("s.exr", exr_bytes())}, data=noisy)
               for _ in range(2)]
    assert replies[0].content == replies[1].content
    assert json.loads(replies[0].headers["X-Mcam-Params"])["seed"] == 0
