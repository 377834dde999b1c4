"""The API's docs pages, Swagger UI and ReDoc, from fastapi-offline's packaged assets (no CDN).
When reads need a token, a page opened with ``?token=`` fetches the schema with it."""

from urllib.parse import quote

from fastapi import APIRouter, Request
from fastapi.openapi.docs import get_redoc_html, get_swagger_ui_html
from fastapi.responses import HTMLResponse

__all__ = ["router"]

router = APIRouter(include_in_schema=False)

ASSETS = "/static-offline-docs"  # where FastAPIOffline mounts them
FAVICON = "/static/favicon.svg"


@router.get("/docs")
async def read_swagger_ui(request: Request) -> HTMLResponse:
    return get_swagger_ui_html(
        openapi_url=_schema(request),
        title="Vantage - Swagger UI",
        swagger_js_url=f"{ASSETS}/swagger-ui-bundle.js",
        swagger_css_url=f"{ASSETS}/swagger-ui.css",
        swagger_favicon_url=FAVICON,
    )


@router.get("/redoc")
async def read_redoc(request: Request) -> HTMLResponse:
    return get_redoc_html(
        openapi_url=_schema(request),
        title="Vantage - ReDoc",
        redoc_js_url=f"{ASSETS}/redoc.standalone.js",
        redoc_favicon_url=FAVICON,
        with_google_fonts=False,
    )


def _schema(request: Request) -> str:
    """The schema's URL, with the page's token if it came with one."""
    token = request.query_params.get("token")
    return "/openapi.json" + (f"?token={quote(token, safe='')}" if token else "")
