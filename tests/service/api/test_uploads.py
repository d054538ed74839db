"""service/api/uploads.py: how an upload's file and fields are read, over real HTTP."""

from __future__ import annotations

from collections.abc import Callable

import httpx
import pytest

from tests.service.conftest import exr_bytes, frame_png

Client = Callable[..., httpx.Client]


@pytest.mark.parametrize("route", ["/v1/simulate", "/v1/reconstructions"])
def test_a_multipart_body_sent_as_octet_stream_is_told_its_content_type(
    client: Client, route: str
) -> None:
    """It was read as the raw file: 'convert it to OpenEXR', or 'cannot tell the frame's
    format'."""
    file = exr_bytes() if route == "/v1/simulate" else frame_png()[0]
    multipart = httpx.Request("POST", "http://x", files={"file": ("upload", file)})
    boundary = multipart.headers["Content-Type"].split("boundary=")[1]
    reply = client().post(route, content=multipart.read(),
                          headers={"Content-Type": "application/octet-stream"})
    assert reply.status_code == 415, reply.text
    message = reply.json()["message"]
    assert "multipart/form-data body sent as application/octet-stream" in message
    assert f"'Content-Type: multipart/form-data; boundary={boundary}'" in message


def test_a_raw_file_is_still_read_as_one(client: Client) -> None:
    reply = client().post("/v1/simulate", content=exr_bytes(),
                          headers={"Content-Type": "application/octet-stream"})
    assert reply.status_code == 200, reply.text


@pytest.mark.parametrize("route", ["/v1/simulate", "/v1/reconstructions"])
def test_a_file_sent_as_a_text_field_is_told_to_be_sent_as_a_file(
    client: Client, route: str
) -> None:
    """``curl -F file=<frame.png`` (or a part with no ``filename``) sends the field
    ``file`` as text: it was told that no file came and to send it in the field 'file',
    which it had."""
    file = exr_bytes() if route == "/v1/simulate" else frame_png()[0]
    reply = client().post(route, files={"file": (None, file)})
    assert reply.status_code == 422, reply.text
    message = reply.json()["message"]
    assert "the field 'file' came as text" in message
    assert "curl -F file=@" in message


@pytest.mark.parametrize("route", ["/v1/simulate", "/v1/reconstructions", "/v1/videos"])
def test_an_empty_file_is_called_empty(client: Client, route: str) -> None:
    """The wording ``mcam`` shares (:func:`models.file_magic.refuse_empty`)."""
    reply = client().post(route, files={"file": ("clip.npy", b"")})
    assert reply.status_code == 422, reply.text
    assert reply.json()["message"] == "the uploaded file is empty; send the whole file"
