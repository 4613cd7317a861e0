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


def _policy(response) -> dict[str, list[str]]:
    return {d.split()[0]: d.split()[1:] for d in response.headers["content-security-policy"].split(";") if d.strip()}


def test_every_response_carries_the_security_headers(client):
    """The page, its files, API answers and refusals alike: never framed, never sniffed, and a CSP
    allowing only this server's files (the page shows frames as blob: images)."""
    answers = [client.get("/"), client.get("/static/app.js"), client.get("/status"), client.get("/openapi.json"),
               client.get("/no-such-route"), client.post("/session/blank"),  # 404, 401 (no token)
               client.get("/status", headers={"Host": "evil.example"})]  # 400 from the Host check
    assert [r.status_code for r in answers][-3:] == [404, 401, 400]
    for r in answers:
        assert r.headers["x-frame-options"] == "DENY" and r.headers["x-content-type-options"] == "nosniff", r.url
        policy = _policy(r)
        assert policy["default-src"] == ["'self'"] and policy["frame-ancestors"] == ["'none'"], r.url
        assert "script-src" not in policy and "style-src" not in policy  # nothing inline, nothing foreign
        assert policy["img-src"] == ["'self'", "blob:", "data:"] and policy["object-src"] == ["'none'"]


def test_the_page_needs_nothing_its_policy_forbids():
    html = (STATIC_DIR / "index.html").read_text()
    assert not re.search(r"<script>|<style|\sstyle=|\son[a-z]+=|javascript:", html)  # no inline script or style
    js = (STATIC_DIR / "app.js").read_text()
    assert not re.search(r"\beval\(|new Function|innerHTML|setAttribute\(\s*[\"']style|\.cssText", js)


def test_docs_pages_allow_their_own_inline_script_by_hash_only(client):
    import base64
    import hashlib

    for path, evals in (("/docs", False), ("/docs/oauth2-redirect", False), ("/redoc", True)):
        r = client.get(path)
        policy = _policy(r)
        inline = re.findall(r"<script>(.*?)</script>", r.text, re.S)
        hashes = [f"'sha256-{base64.b64encode(hashlib.sha256(s.encode()).digest()).decode()}'" for s in inline]
        assert policy["script-src"] == ["'self'", *hashes, *(["'unsafe-eval'"] if evals else [])], path
        assert "'unsafe-inline'" not in policy["script-src"] and policy["frame-ancestors"] == ["'none'"]
        assert r.headers["x-frame-options"] == "DENY" and r.headers["x-content-type-options"] == "nosniff"
    assert len(re.findall(r"<script>", client.get("/docs").text)) == 1  # Swagger UI's start-up script


def test_the_page_may_reach_the_operator_port_and_nothing_else():
    """With an operator port the page's policy adds it, at each name the page may be reached by,
    to what it may connect to (its blank goes there first); without one the policy is as before."""
    from server.pages import PAGE_CSP, page_csp

    csp = page_csp(["127.0.0.1", "localhost", "::1", "*"], 8766)
    assert csp == PAGE_CSP + "; connect-src 'self' http://127.0.0.1:8766 http://[::1]:8766 http://localhost:8766"
    assert page_csp(["127.0.0.1"], None) == PAGE_CSP
