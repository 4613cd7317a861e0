"""The operator page and the API docs are served from local files: nothing points at a CDN."""

from __future__ import annotations

import re

from server.pages import STATIC_DIR


def test_operator_page_and_its_assets_are_served(client):
    page = client.get("/")
    assert page.status_code == 200 and "text/html" in page.headers["content-type"]
    assets = re.findall(r'(?:src|href)="(/static/[^"]+)"', page.text)
    assert {"/static/app.js", "/static/style.css"} <= set(assets)
    for path in assets:
        r = client.get(path)
        assert r.status_code == 200 and r.content == (STATIC_DIR / path.removeprefix("/static/")).read_bytes()


def test_page_keeps_the_token_out_of_urls():
    js = (STATIC_DIR / "app.js").read_text()
    assert "sessionStorage" in js and "localStorage" not in js
    assert re.search(r'"Authorization"\]\s*=\s*"Bearer "', js)
    assert "token=" not in js and "?token" not in js


def test_no_external_urls_in_the_page():
    for f in STATIC_DIR.iterdir():
        assert not re.search(r"https?://", f.read_text()), f"{f.name} refers to another host"


def test_docs_and_redoc_load_their_assets_locally(client):
    for path in ("/docs", "/redoc"):
        html = client.get(path).text
        urls = re.findall(r'(?:src|href)="([^"]+)"', html)
        assert urls, path
        for url in urls:
            assert url.startswith("/"), f"{path} loads {url} from another host"
            assert client.get(url).status_code == 200, url
        assert "fonts.googleapis" not in html
    assert client.get("/openapi.json").json()["components"]["schemas"]["SettingsModel"]["properties"]["alpha"]
