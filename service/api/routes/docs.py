"""``GET /docs``: the API's interactive documentation (Swagger UI), served by this server.

FastAPI's default page loads Swagger UI from a CDN, floating across a major version:
it fails on a rig's offline network, and a compromised release would run on the origin
where the web viewer keeps its API key. Here the page and its assets (the
``swagger-ui-bundle-v2`` wheel, mounted at :data:`ASSETS`) come from this server, with
a Content Security Policy that allows no other origin.
"""

from __future__ import annotations

from fastapi import APIRouter
from fastapi.openapi.docs import get_swagger_ui_html
from fastapi.responses import HTMLResponse

from service.api.security_headers import DOCS_HEADERS

router = APIRouter(tags=["docs"])
#: Where the Swagger UI files are mounted (see :func:`service.main.create_app`).
ASSETS = "/docs/assets"


@router.get("/docs", include_in_schema=False)
def docs() -> HTMLResponse:
    page = get_swagger_ui_html(
        openapi_url="/openapi.json",
        title="MantissaCam API",
        swagger_js_url=f"{ASSETS}/swagger-ui-bundle.js",
        swagger_css_url=f"{ASSETS}/swagger-ui.css",
        swagger_favicon_url=f"{ASSETS}/favicon-32x32.png",
    )
    page.headers.update(DOCS_HEADERS)
    return page
