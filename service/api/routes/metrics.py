"""``GET /metrics``: Prometheus text format (see :mod:`service.api.telemetry`).

It names the devices and shows the service's load, so it needs an API key with the
``read`` scope (a Prometheus scrape job sends it as ``authorization: credentials``),
unless ``MCAM_METRICS_PUBLIC`` opens it to a scraper on a private network.
"""

from __future__ import annotations

from fastapi import APIRouter, Request, Response
from prometheus_client import CONTENT_TYPE_LATEST, CollectorRegistry, generate_latest

from service.api.deps import Credentials, StateDep, require
from service.api.schemas import AUTH_ERRORS

router = APIRouter(tags=["ops"])


@router.get(
    "/metrics",
    response_class=Response,
    responses={
        200: {"content": {CONTENT_TYPE_LATEST: {}}, "description": "Prometheus text"},
        **AUTH_ERRORS,
    },
    summary="Request, queue-wait, decode and encode histograms; queue depth; jobs by state",
)
def metrics(request: Request, state: StateDep, credentials: Credentials) -> Response:
    if not state.settings.metrics_public:
        require("read")(request, state, credentials)
    registry: CollectorRegistry = request.app.state.metrics_registry
    return Response(generate_latest(registry), media_type=CONTENT_TYPE_LATEST)
