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
