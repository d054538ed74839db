"""Query parameters and form fields given more than once, over real HTTP."""

from __future__ import annotations

from collections.abc import Callable

import httpx
import pytest

from tests.service.conftest import exr_bytes

Client = Callable[..., httpx.Client]
JOB = "0" * 32


@pytest.mark.parametrize(
    ("method", "target", "name"),
    [
        ("GET", f"/v1/jobs/{JOB}/result?part=image&part=winding", "part"),
        ("GET", f"/v1/jobs/{JOB}/result?format=png&exposure=1&exposure=2", "exposure"),
        ("POST", "/v1/simulate?gain=2&gain=3", "gain"),
    ],
)
def test_a_query_parameter_given_twice_is_refused(
    client: Client, method: str, target: str, name: str
) -> None:
    """It was read as its last value: the W map for part=image&part=winding, a frame
    simulated at gain 3 for gain=2&gain=3."""
    body = exr_bytes() if method == "POST" else None
    headers = {"Content-Type": "application/octet-stream"} if body else {}
    reply = client().request(method, target, content=body, headers=headers)
    assert reply.status_code == 422, reply.text
    assert reply.json()["code"] == "invalid_input"
    assert f"{name}: given 2 times" in reply.json()["message"]
    assert "give it once" in reply.json()["message"]


def test_a_parameter_repeated_many_times_names_a_few_of_its_values(client: Client) -> None:
    query = "&".join(f"exposure={ev}" for ev in range(1000))
    reply = client().get(f"/v1/jobs/{JOB}/result?{query}")
    assert reply.status_code == 422
    assert "given 1000 times ('0', '1', '2', ...)" in reply.json()["message"]
    assert len(reply.content) < 1_000


def test_a_form_field_given_twice_is_refused(client: Client) -> None:
    """-F gain=2 -F gain=3 simulated the frame at gain 3."""
    reply = client().post(
        "/v1/simulate", files=[("file", ("scene.exr", exr_bytes())), ("gain", (None, "2")),
                               ("gain", (None, "3"))],
    )  # fmt: skip
    assert reply.status_code == 422, reply.text
    message = reply.json()["message"]
    assert "gain: given 2 times ('2', '3'); give it once" in message
    assert "JSON" not in message


@pytest.mark.parametrize("where", ["query", "form"])
def test_a_list_given_as_repeated_values_is_told_to_be_comma_separated(
    client: Client, where: str
) -> None:
    """-F outputs=hdr10 -F outputs=sdr was told 'give it once', which reads as 'pick
    one'; a video's outputs are one comma-separated value."""
    fields = [("outputs", (None, "hdr10")), ("outputs", (None, "sdr"))]
    query = "?outputs=hdr10&outputs=sdr" if where == "query" else ""
    reply = client().post(
        f"/v1/videos{query}", files=[("file", ("clip.npy", b"x")), *(fields * (where == "form"))]
    )
    assert reply.status_code == 422, reply.text
    assert "outputs: given 2 times ('hdr10', 'sdr'); give it once, its values " \
        "comma-separated: outputs=hdr10,sdr" in reply.json()["message"]


@pytest.mark.parametrize(
    ("target", "name", "takes"),
    [
        (f"/v1/jobs/{JOB}/result?format=png&exposur=2", "exposur", "exposure, format, part"),
        (f"/v1/jobs/{JOB}/result?fromat=png", "fromat", "exposure, format, part"),
        ("/v1/devices/cam1/events?sinse=0", "sinse", "limit, since"),
        ("/v1/devices/cam1/frames/latest?formt=png", "formt", "exposure, format"),
    ],
)
def test_a_query_parameter_the_route_does_not_take_is_refused(
    client: Client, target: str, name: str, takes: str
) -> None:
    """A misspelt exposure was ignored (the preview came at EV 0), a misspelt format gave
    the EXR, while the upload routes refused a parameter they do not take."""
    reply = client().get(target)
    assert reply.status_code == 422, reply.text
    assert reply.json()["code"] == "invalid_input"
    message = reply.json()["message"]
    assert f"{name}: not a query parameter of GET " in message and takes in message


def test_the_parameters_a_route_takes_are_accepted(client: Client) -> None:
    """Every parameter a result takes, given once: the job's 404, not a 422; a route
    that declares no query parameter is left to read its query itself."""
    reply = client().get(f"/v1/jobs/{JOB}/result?part=image&format=png&exposure=1")
    assert reply.status_code == 404, reply.text
    reply = client().get(f"/v1/jobs/{JOB}?cache_buster=1")
    assert reply.status_code == 404, reply.text
    reply = client().post("/v1/simulate?gain=2&format=npy", content=exr_bytes(),
                          headers={"Content-Type": "application/octet-stream"})
    assert reply.status_code == 200, reply.text


def test_a_long_unknown_or_repeated_name_is_not_echoed_whole(client: Client) -> None:
    name = "x" * 10_000
    for query in (f"{name}=1", f"{name}=1&{name}=2"):
        reply = client().get(f"/v1/jobs/{JOB}/result?{query}")
        assert reply.status_code == 422
        assert len(reply.content) < 2_000 and "(and 9920 more characters)" in reply.text
