"""The FastAPI application: ``create_app(settings)`` wires routers, errors, limits and metrics.

Each resource's router lives in its own module under ``service/api/routes``
and is listed once in :data:`ROUTERS`; the web viewer is served at ``/`` with a
Content Security Policy (:mod:`service.api.security_headers`), behind the API's own
404s and 405s (:mod:`service.api.viewer_mount`).
"""

from __future__ import annotations

import importlib
import logging
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from pathlib import Path

from fastapi import Depends, FastAPI
from fastapi.staticfiles import StaticFiles
from starlette.concurrency import run_in_threadpool
from starlette.routing import BaseRoute
from swagger_ui_bundle import swagger_ui_path

from models.decoders.registry import available_decoders
from service.api.body_limit import BodyLimitMiddleware
from service.api.body_timeout import BodyTimeoutMiddleware
from service.api.errors import install_error_handlers
from service.api.head_requests import HeadRequestMiddleware
from service.api.request_target import RequestTargetMiddleware
from service.api.routes.docs import ASSETS as DOCS_ASSETS
from service.api.security_headers import API_HEADERS, VIEWER_HEADERS, SecurityHeaders
from service.api.single_values import known_query_names, single_query_values
from service.api.state import ServiceState, open_state
from service.api.telemetry import RequestTimer, build_registry
from service.api.viewer_mount import ViewerMount
from service.core.config import Settings, get_settings
from service.core.security import KeyRing

log = logging.getLogger(__name__)

#: Router modules (each exposes ``router``), in the order the API docs list them.
ROUTERS: tuple[str, ...] = (
    "service.api.routes.simulate",
    "service.api.routes.reconstructions",
    "service.api.routes.jobs",
    "service.api.routes.decoders",
    "service.api.routes.health",
    "service.api.routes.metrics",
    "service.api.routes.devices",
    "service.api.routes.device_events",
    "service.api.routes.videos",
    "service.api.routes.recordings",
    "service.api.routes.docs",
)
STATIC_DIR = Path(__file__).parent / "static"
API_VERSION = "1.0.0"


def create_app(settings: Settings | None = None) -> FastAPI:
    """The API app. Redis is connected (or the embedded one started) at startup."""
    settings = settings or get_settings()
    keyring, new_key = KeyRing.from_settings(settings)
    if new_key is not None:
        log.warning("generated an API key, stored in %s", settings.data_dir / "api_keys")

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        state = await run_in_threadpool(open_state, settings, keyring)
        app.state.mcam = state
        await run_in_threadpool(available_decoders)  # import the providers before requests
        try:
            yield
        finally:
            await run_in_threadpool(state.close)

    app = FastAPI(
        title="MantissaCam",
        version=API_VERSION,
        summary="Snapshot HDR from wrapping sensors: simulate, reconstruct, inspect jobs",
        lifespan=lifespan,
        docs_url=None,  # served from this server by service.api.routes.docs
        redoc_url=None,
    )
    app.state.settings = settings
    install_error_handlers(app)
    routers = [importlib.import_module(name).router for name in ROUTERS]
    for router in routers:
        app.include_router(
            router, dependencies=[Depends(single_query_values), Depends(known_query_names)]
        )
    # The API's routes with their full path templates (a router's paths carry its prefix).
    routes: list[BaseRoute] = [route for router in routers for route in router.routes]

    def current_state() -> ServiceState:
        state: ServiceState = app.state.mcam
        return state

    registry, requests = build_registry(current_state)
    app.state.metrics_registry = registry
    app.add_middleware(BodyLimitMiddleware, limit=settings.max_upload_bytes,
                       json_limit=settings.max_json_bytes)
    app.add_middleware(BodyTimeoutMiddleware, timeout_s=settings.http_body_timeout_s,
                       deadline_s=settings.http_body_deadline_s)
    app.add_middleware(HeadRequestMiddleware)
    app.add_middleware(RequestTargetMiddleware)
    app.add_middleware(RequestTimer, histogram=requests, routes=routes)
    app.add_middleware(SecurityHeaders, headers=API_HEADERS)
    app.mount(DOCS_ASSETS, StaticFiles(directory=swagger_ui_path), name="docs-assets")
    viewer = SecurityHeaders(StaticFiles(directory=STATIC_DIR, html=True), VIEWER_HEADERS)
    # FastAPI's own /openapi.json is the API's too, not a viewer file (its 405 said so).
    schema = [route for route in app.routes if getattr(route, "path", None) == app.openapi_url]
    app.mount("/", ViewerMount(viewer, [*routes, *schema]), name="viewer")
    return app
