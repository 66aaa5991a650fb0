"""The API reference: ``/openapi.json``, Swagger UI at ``/docs``, ReDoc at ``/redoc``.

FastAPI's own pages load Swagger UI and ReDoc from a CDN, so they are blank on a machine
without internet, and they are served without the token. These routes replace them: the
JavaScript and CSS come from the ``fastapi-offline`` package (Swagger UI, Apache-2.0; ReDoc,
MIT; served at ``/docs-assets``, public like the page's own ``/static``), and the pages and
the schema need the token when one is set (a page opened with ``?token=`` keeps it in the
same cookie as our page, which then rides along with the schema fetch and "Try it out").
"""

from __future__ import annotations

from pathlib import Path

from fastapi import APIRouter, Request
from fastapi.openapi.docs import get_redoc_html, get_swagger_ui_html, get_swagger_ui_oauth2_redirect_html
from fastapi.responses import HTMLResponse, JSONResponse, Response
from fastapi.staticfiles import StaticFiles

from server.deps import require_token, token_ok
from server.routes_pages import locked_page, with_token_cookie

router = APIRouter(include_in_schema=False)

ASSETS_URL = "/docs-assets"
OPENAPI_URL = "/openapi.json"
OAUTH2_REDIRECT_URL = "/docs/oauth2-redirect"


def assets_dir() -> Path:
    """Swagger UI's and ReDoc's files as the ``fastapi-offline`` package ships them."""
    import fastapi_offline

    return Path(fastapi_offline.__file__).resolve().parent / "static"


def mount_assets(app) -> None:
    app.mount(ASSETS_URL, StaticFiles(directory=assets_dir()), name="docs-assets")


@router.get(OPENAPI_URL)
def openapi_schema(request: Request) -> Response:
    require_token(request)
    return JSONResponse(request.app.openapi())


@router.get("/docs")
def swagger_ui(request: Request) -> Response:
    if not token_ok(request):
        return locked_page()
    page = get_swagger_ui_html(
        openapi_url=OPENAPI_URL, title=f"{request.app.title} - API reference",
        oauth2_redirect_url=OAUTH2_REDIRECT_URL, swagger_js_url=f"{ASSETS_URL}/swagger-ui-bundle.js",
        swagger_css_url=f"{ASSETS_URL}/swagger-ui.css", swagger_favicon_url=f"{ASSETS_URL}/favicon.png",
        # No online validator badge: it would send the schema's URL to a third party.
        swagger_ui_parameters={"validatorUrl": None})
    return with_token_cookie(page, request)


@router.get(OAUTH2_REDIRECT_URL)
def swagger_ui_redirect(request: Request) -> HTMLResponse:
    require_token(request)
    return get_swagger_ui_oauth2_redirect_html()


@router.get("/redoc")
def redoc(request: Request) -> Response:
    if not token_ok(request):
        return locked_page()
    page = get_redoc_html(openapi_url=OPENAPI_URL, title=f"{request.app.title} - API reference (ReDoc)",
                          redoc_js_url=f"{ASSETS_URL}/redoc.standalone.js",
                          redoc_favicon_url=f"{ASSETS_URL}/favicon.png", with_google_fonts=False)
    return with_token_cookie(page, request)
