"""The ASGI app, ``app.main:app``: assembles routers, error translation and start-up."""

from collections.abc import AsyncIterator
from contextlib import asynccontextmanager

from fastapi import FastAPI, Request
from fastapi.responses import JSONResponse

from .config import get_settings
from .documents import Registry
from .routers import documents, health, items, stream, viewport
from .store import Store


@asynccontextmanager
async def lifespan(app: FastAPI) -> AsyncIterator[None]:
    store = Store(get_settings().data_dir)
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


@app.exception_handler(KeyError)
async def not_found(request: Request, error: KeyError) -> JSONResponse:
    """Unknown documents and items are 404s that say which."""
    return JSONResponse({"detail": error.args[0] if error.args else "not found"}, status_code=404)
