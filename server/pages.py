"""The operator page at `/` and the API docs at /docs and /redoc, all from files inside installed
packages, so a lab PC without internet gets the same pages.

The page is plain HTML/JS/CSS in `server/static/` (no build step). Swagger UI and ReDoc come from
the `fastapi-offline` package's bundled copies, served by FastAPI's documented offline recipe.

Content-Security-Policy: the page and every other response get `PAGE_CSP` (this server's files
only; images also as blob: and data: URLs, as the page shows each frame from a blob). The docs
pages get `_docs_csp`: FastAPI writes their start-up script inline (allowed by its hash), Swagger
UI and ReDoc add style elements as they render, ReDoc runs its search in a blob: worker and
compiles JSON schemas into functions (eval, on /redoc only).
"""

from __future__ import annotations

import base64
import hashlib
import re
from pathlib import Path

from fastapi import FastAPI
from fastapi.openapi.docs import get_redoc_html, get_swagger_ui_html, get_swagger_ui_oauth2_redirect_html
from fastapi.responses import FileResponse, HTMLResponse
from fastapi.staticfiles import StaticFiles

__all__ = ["PAGE_CSP", "STATIC_DIR", "add_pages", "page_csp"]

STATIC_DIR = Path(__file__).with_name("static")
PAGE_CSP = ("default-src 'self'; img-src 'self' blob: data:; object-src 'none'; base-uri 'none'; "
            "form-action 'self'; frame-ancestors 'none'")


def page_csp(trusted_hosts, operator_port: int | None) -> str:
    """`PAGE_CSP`, plus the operator port at each name the page may be reached by (the page sends
    its blank there first: it answers while this server is flooded)."""
    if operator_port is None:
        return PAGE_CSP
    names = sorted({f"[{h}]" if ":" in h and not h.startswith("[") else h for h in trusted_hosts if h != "*"})
    allowed = " ".join(f"http://{h}:{operator_port}" for h in names)
    return PAGE_CSP + f"; connect-src 'self' {allowed}"


def _docs_csp(page: HTMLResponse, *, eval_: bool = False) -> HTMLResponse:
    """`page` with its policy: its inline scripts by hash (nothing else inline runs)."""
    scripts = re.findall(rb"<script>(.*?)</script>", page.body, re.S)
    allowed = "".join(f" 'sha256-{base64.b64encode(hashlib.sha256(s).digest()).decode()}'" for s in scripts)
    allowed += " 'unsafe-eval'" if eval_ else ""
    page.headers["Content-Security-Policy"] = (
        f"default-src 'self'; script-src 'self'{allowed}; "
        "style-src 'self' 'unsafe-inline'; img-src 'self' data: blob:; worker-src 'self' blob:; "
        "object-src 'none'; base-uri 'none'; form-action 'self'; frame-ancestors 'none'")
    return page


def _docs_assets() -> Path:
    import fastapi_offline

    return Path(fastapi_offline.__file__).with_name("static")


def add_pages(app: FastAPI) -> None:
    """Mount the page and the offline docs on `app` (built with docs_url=None, redoc_url=None)."""
    app.mount("/static", StaticFiles(directory=STATIC_DIR), name="static")
    app.mount("/docs-assets", StaticFiles(directory=_docs_assets()), name="docs-assets")
    title = app.title

    @app.get("/", include_in_schema=False)
    async def operator_page() -> FileResponse:
        return FileResponse(STATIC_DIR / "index.html", headers={"Cache-Control": "no-cache"})

    @app.get("/docs", include_in_schema=False)
    async def swagger_ui() -> HTMLResponse:
        return _docs_csp(get_swagger_ui_html(openapi_url=app.openapi_url, title=f"{title} – API docs",
                                             oauth2_redirect_url="/docs/oauth2-redirect",
                                             swagger_js_url="/docs-assets/swagger-ui-bundle.js",
                                             swagger_css_url="/docs-assets/swagger-ui.css",
                                             swagger_favicon_url="/docs-assets/favicon.png"))

    @app.get("/docs/oauth2-redirect", include_in_schema=False)
    async def swagger_ui_redirect() -> HTMLResponse:
        return _docs_csp(get_swagger_ui_oauth2_redirect_html())

    @app.get("/redoc", include_in_schema=False)
    async def redoc() -> HTMLResponse:
        return _docs_csp(get_redoc_html(openapi_url=app.openapi_url, title=f"{title} – ReDoc",
                                        redoc_js_url="/docs-assets/redoc.standalone.js",
                                        redoc_favicon_url="/docs-assets/favicon.png", with_google_fonts=False),
                         eval_=True)
