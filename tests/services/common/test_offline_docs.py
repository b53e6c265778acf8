"""``/docs`` and ``/redoc`` of every service reference only the service's own URLs, and those are served."""

from __future__ import annotations

import re
from collections.abc import Callable
from pathlib import Path

import pytest
from fastapi import FastAPI
from fastapi.testclient import TestClient

from services.common.docs import ASSETS_URL, add_offline_docs
from services.controller.app import create_app as controller_app
from services.controller.settings import Settings as ControllerSettings
from services.emulator.app import create_app as emulator_app
from services.emulator.settings import Settings as EmulatorSettings
from services.web.app import create_app as web_app
from services.web.settings import Settings as WebSettings

URL_ATTR = re.compile(r"""(?:src|href|spec-url)\s*=\s*["']([^"']+)["']""")
QUOTED_URL = re.compile(r"""url:\s*'([^']+)'""")


def emulator(tmp: Path) -> FastAPI:
    return emulator_app(EmulatorSettings(artifacts_dir=tmp))


def controller(tmp: Path) -> FastAPI:
    # Redis is connected lazily: the docs need none
    return controller_app(ControllerSettings(artifacts_dir=tmp, redis_url="redis://127.0.0.1:1/0"))


def web(tmp: Path) -> FastAPI:
    return web_app(WebSettings(artifacts_dir=tmp, web_dist=tmp / "dist"))


SERVICES: dict[str, Callable[[Path], FastAPI]] = {"emulator": emulator, "controller": controller, "web": web}


def page_urls(html: str) -> list[str]:
    return URL_ATTR.findall(html) + QUOTED_URL.findall(html)


@pytest.mark.parametrize("service", sorted(SERVICES))
@pytest.mark.parametrize("page", ["/docs", "/redoc"])
def test_docs_pages_use_only_local_assets(service: str, page: str, tmp_path: Path) -> None:
    with TestClient(SERVICES[service](tmp_path)) as client:
        r = client.get(page)
        assert r.status_code == 200, r.text
        html = r.text
        assert "http://" not in html and "https://" not in html, html  # no CDN, no web fonts
        urls = page_urls(html)
        assert urls, html
        scripts = [u for u in urls if u.endswith(".js")]
        assert scripts and all(u.startswith(f"{ASSETS_URL}/") for u in scripts), urls
        for url in urls:
            assert url.startswith("/"), url
            got = client.get(url)
            assert got.status_code == 200, url
            assert len(got.content) > 1000, url
        assert client.get("/openapi.json").json()["info"]["title"].startswith("NeuroAnimator")


def test_docs_assets_are_javascript_and_css(tmp_path: Path) -> None:
    with TestClient(web(tmp_path)) as client:
        js = client.get(f"{ASSETS_URL}/swagger-ui-bundle.js")
        css = client.get(f"{ASSETS_URL}/swagger-ui.css")
        redoc = client.get(f"{ASSETS_URL}/redoc.standalone.js")
    assert "javascript" in js.headers["content-type"] and "SwaggerUIBundle" in js.text
    assert css.headers["content-type"].startswith("text/css")
    assert "javascript" in redoc.headers["content-type"] and "Redoc" in redoc.text
    assert "cdn.redoc.ly" not in redoc.text  # Redocly's logo: an empty image instead


def test_docs_behind_a_path_prefix() -> None:
    """Behind a proxy that strips ``/api/emulator`` (``root_path``), the pages name the prefixed URLs."""
    app = FastAPI(docs_url=None, redoc_url=None)
    add_offline_docs(app)
    with TestClient(app, root_path="/api/emulator") as client:
        html = client.get("/docs").text
    assert f"/api/emulator{ASSETS_URL}/swagger-ui-bundle.js" in html
    assert "'/api/emulator/openapi.json'" in html


def test_fastapi_cdn_pages_must_be_off() -> None:
    with pytest.raises(ValueError, match="docs_url=None"):
        add_offline_docs(FastAPI())
