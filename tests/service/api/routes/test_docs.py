"""/docs (Swagger UI served by this server, under a policy that allows no other origin)
and what the OpenAPI document and the README say of each route's errors."""

from __future__ import annotations

import ast
import importlib
import inspect
import re
from pathlib import Path
from types import ModuleType

import httpx
import pytest
from fastapi.routing import APIRoute

from models.errors import OutputOverflowError, OutputUnderflowError
from service.api.errors import STATUS_CODES
from service.core.config import Settings
from service.main import ROUTERS, create_app
from tests.service.static.conftest import chromium, needs_chromium, wait_for_js
from worker.child_process import ChildDiedError
from worker.job_processor import error_of, model_unavailable


def test_the_docs_page_and_its_assets_come_from_this_server(api: str) -> None:
    """FastAPI's page loaded Swagger UI from a CDN (offline rigs got a blank page, and a
    compromised release would run where the viewer keeps its key)."""
    page = httpx.get(f"{api}/docs")
    assert page.status_code == 200 and page.headers["content-type"].startswith("text/html")
    assert not re.search(r"(src|href)=['\"]https?://", page.text), "an external asset"
    policy = page.headers["content-security-policy"]
    assert "default-src 'self'" in policy and "http" not in policy
    assets = re.findall(r"(?:src|href)=['\"](/[^'\"]+)", page.text)
    suffixes = {asset.rsplit(".", 1)[-1] for asset in assets}
    assert len(assets) >= 2 and {"js", "css"} <= suffixes, f"assets found: {assets}"
    for asset in assets:
        assert httpx.get(f"{api}{asset}").status_code == 200, asset
    assert httpx.get(f"{api}/redoc").status_code == 404  # Redoc came from a CDN too


@needs_chromium
def test_the_docs_render_the_api_in_a_browser_offline(api: str) -> None:
    with chromium() as browser:
        page = browser.new_page()
        origins: set[str] = set()
        page.on("request", lambda request: origins.add(request.url.split("/")[2]))
        errors: list[str] = []
        page.on("console", lambda m: errors.append(m.text) if m.type == "error" else None)
        page.goto(f"{api}/docs")
        wait_for_js(page, """() => [...document.querySelectorAll('.opblock-summary-path')]
                             .some(e => e.textContent.includes('/v1/reconstructions'))""")
        assert origins == {api.split("/")[2]}
        assert not [e for e in errors if "Content Security Policy" in e]


#: What the OpenAPI document must say of a route's error statuses: words naming each code
#: the route can answer with that status (grepped from the routes, ``service.api.deps``,
#: ``service.api.uploads``, the body limits and the Redis handlers of
#: ``service.api.errors``).
ANSWERED = [
    ("get", "/v1/devices/{device_id}/recordings", "404", "never recorded"),
    ("post", "/v1/devices/{device_id}/control", "503", "control_backlog_full"),
    ("post", "/v1/devices/{device_id}/control", "503", "Redis"),
    ("post", "/v1/devices/{device_id}/control", "413", "body_too_large"),
    ("post", "/v1/devices/{device_id}/control", "400", "bad_request"),
    ("post", "/v1/devices/{device_id}/recordings", "413", "body_too_large"),
    ("post", "/v1/devices/{device_id}/recordings", "409", "recording_failed"),
    ("delete", "/v1/devices/{device_id}", "409", "device_busy"),
    ("delete", "/v1/jobs/{job_id}", "409", "job_finished"),
    ("get", "/v1/jobs/{job_id}/result", "409", "video_job"),
    ("get", "/v1/jobs/{job_id}/result", "503", "server_busy"),
    ("get", "/v1/devices/{device_id}/frames/latest", "503", "server_busy"),
    ("get", "/v1/devices/{device_id}/frames/latest", "404", "no reconstructed frame"),
    ("get", "/v1/videos/{job_id}/result", "409", "output_not_made"),
    ("post", "/v1/reconstructions", "429", "too_many_jobs"),
    ("post", "/v1/reconstructions", "503", "queue_full"),
    ("post", "/v1/videos", "503", "queue_full"),
    ("post", "/v1/simulate", "503", "server_busy"),
    ("delete", "/v1/jobs/{job_id}", "503", "store_full"),
    ("delete", "/v1/devices/{device_id}", "503", "store_full"),
    ("post", "/v1/devices/{device_id}/recordings", "503", "store_full"),
    *[
        ("get", path, status, words)
        for path in (
            "/v1/jobs/{job_id}/result",
            "/v1/videos/{job_id}/result",
            "/v1/devices/{device_id}/frames/latest",
        )
        for status, words in (
            ("206", "Range"),
            ("304", "If-None-Match"),
            ("400", "bad_range"),
            ("412", "precondition_failed"),
            ("416", "range_not_satisfiable"),
        )
    ],
]
#: Codes a route's document named although the route can never answer them.
NEVER_ANSWERED = [
    ("post", "/v1/simulate", "429", "too_many_jobs"),  # it queues no job
    ("post", "/v1/simulate", "503", "full"),
    # a full Redis refuses writes only: reads go on (tests/service/api/test_store_full.py)
    ("get", "/v1/jobs/{job_id}", "503", "full"),
    ("get", "/v1/decoders", "503", "full"),
    ("get", "/v1/devices/{device_id}", "503", "full"),
    ("get", "/v1/devices/{device_id}/recordings", "503", "full"),
]


def _description(settings: Settings, method: str, path: str, status: str) -> str:
    """The OpenAPI description of ``status`` for the operation (empty if undocumented)."""
    operation = create_app(settings).openapi()["paths"][path][method]
    return str(operation["responses"].get(status, {}).get("description", ""))


@pytest.mark.parametrize(("method", "path", "status", "words"), ANSWERED)
def test_the_openapi_names_each_error_a_route_answers(
    settings: Settings, method: str, path: str, status: str, words: str
) -> None:
    """A route's responses merged from shared dicts lost the route's own words (the
    recordings' 404, the control's 503); the JSON routes' 413 ``body_too_large`` and the
    control's 400 were not documented, nor ``queue_full``, ``device_busy`` and
    ``job_finished`` named; the newest frame's 404 said only "no such device"; the file
    routes named none of their answers to Range and conditional requests (206, 304,
    ``bad_range``, ``precondition_failed``, ``range_not_satisfiable``)."""
    assert words in _description(settings, method, path, status)


def _raised_codes(module: ModuleType) -> set[tuple[int, str]]:
    """``(status, code)`` of each ``ApiError(status, "code", ...)`` in ``module``'s source
    whose status and code are literals."""
    found = set()
    for node in ast.walk(ast.parse(Path(inspect.getfile(module)).read_text())):
        if isinstance(node, ast.Call) and getattr(node.func, "id", None) == "ApiError":
            status, code = node.args[:2]
            if isinstance(status, ast.Constant) and isinstance(code, ast.Constant):
                found.add((status.value, code.value))
    return found


@pytest.mark.parametrize("name", ROUTERS)
def test_every_code_a_router_raises_is_named_in_its_documented_responses(name: str) -> None:
    """Each route-specific code a router's module raises (not the status's own code, such
    as ``not_found`` for 404) is named in the description of that status on one of its
    routes: DELETE /v1/jobs/{id}'s 409 did not name ``job_finished``."""
    module = importlib.import_module(name)
    described = [
        str(route.responses.get(status, {}).get("description", ""))
        for route in module.router.routes
        if isinstance(route, APIRoute)
        for status in route.responses
    ]
    missing = [
        (status, code)
        for status, code in sorted(_raised_codes(module))
        if code != STATUS_CODES.get(status) and not any(code in text for text in described)
    ]
    assert missing == []


@pytest.mark.parametrize(("method", "path", "status", "code"), NEVER_ANSWERED)
def test_the_openapi_names_no_error_a_route_cannot_answer(
    settings: Settings, method: str, path: str, status: str, code: str
) -> None:
    """``POST /v1/simulate`` shared the responses of the routes that queue a job: its 429
    named too_many_jobs and its 503 a full queue, neither of which it can answer; every
    read route's 503 said Redis may be full, which refuses writes only."""
    assert code not in _description(settings, method, path, status)

def test_the_readme_names_every_code_a_failed_job_reports() -> None:
    """``GET /v1/jobs/{id}`` reports a failed job's ``error.code``; the README named only
    model_unavailable and output_overflow of them."""
    codes = {
        ChildDiedError.code,
        OutputOverflowError.code,
        OutputUnderflowError.code,
        error_of(RuntimeError("a bug")).code,
        model_unavailable("itoh", "mantissa", "its id", "retry later").code,
        "worker_lost",
    }
    readme = (Path(__file__).parents[4] / "README.md").read_text()
    assert [code for code in sorted(codes) if f"`{code}`" not in readme] == []
