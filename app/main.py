"""The ASGI app, ``app.main:app``: assembles routers, error translation and start-up."""

from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from pathlib import Path

from fastapi import FastAPI, Request
from fastapi.responses import FileResponse, JSONResponse
from fastapi.middleware.cors import CORSMiddleware
from fastapi.staticfiles import StaticFiles

from .config import get_settings
from .documents import Registry, warm_up
from .routers import documents, health, items, stream, viewport
from .store import Store

STATIC = Path(__file__).resolve().parent.parent / "static"


@asynccontextmanager
async def lifespan(app: FastAPI) -> AsyncIterator[None]:
    store = Store(get_settings().data_dir)
    warm_up()
    app.state.registry = Registry(store)  # loads every document's index from the store
    yield
    store.close()


app = FastAPI(
    title="Vantage",
    summary="Viewport virtualisation for large document canvases.",
    description="**WebSocket** `/documents/{doc}/stream`: " + (stream.__doc__ or ""),
    lifespan=lifespan,
)
for module in (health, documents, items, viewport, stream):
    app.include_router(module.router)
app.mount("/static", StaticFiles(directory=STATIC), name="static")
if origins := [o.strip() for o in get_settings().cors_origins.split(",") if o.strip()]:
    # Tokens travel in a header, not cookies: no credentials, so "*" never meets them.
    app.add_middleware(CORSMiddleware, allow_origins=origins, allow_credentials=False,
                       allow_methods=["GET", "POST", "PUT", "DELETE"], allow_headers=["Authorization", "Content-Type"])  # fmt: skip


@app.get("/", include_in_schema=False)
async def read_page() -> FileResponse:
    """The canvas page: pan and zoom a document (plain JS in ``static/``, no build step)."""
    return FileResponse(STATIC / "index.html")


@app.exception_handler(KeyError)
async def not_found(request: Request, error: KeyError) -> JSONResponse:
    """Unknown documents and items are 404s that say which."""
    return JSONResponse({"detail": error.args[0] if error.args else "not found"}, status_code=404)
