"""/docs: Swagger UI served by this server, under a policy that allows no other origin."""

from __future__ import annotations

import re

import httpx

from tests.service.static.conftest import chromium, needs_chromium, wait_for_js


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
