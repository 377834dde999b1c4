"""The ASGI app: ``create_app(settings)`` assembles the door, routers, error translation and
start-up; ``app.main:app`` is the app for the process's settings, made when first asked for.

Importing this module starts nothing. The process's start-up (:func:`start_up`: the heap's
settings, the kernels loaded or compiled, start-up's objects frozen) runs once, before the
first app of the process answers: when ``app`` is first asked for (``uvicorn app.main:app``,
``vantage serve``, whose supervisor asks before it forks its workers so that they share what
it made), or else as an app's lifespan starts.
"""

import asyncio
import contextlib
import logging
import re
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from importlib import resources
from pathlib import Path
from urllib.parse import unquote_plus

from fastapi import FastAPI, Request
from fastapi.concurrency import run_in_threadpool
from fastapi.middleware.cors import CORSMiddleware
from fastapi.middleware.gzip import GZipMiddleware
from fastapi.responses import FileResponse, JSONResponse
from fastapi.staticfiles import StaticFiles
from fastapi_offline import FastAPIOffline

from .access import Access
from .answers import tile_answered
from .compaction import Compactions
from .config import Settings, get_settings
from .errors import ServiceError
from .guard import Guard
from .heap import map_large_blocks
from .hot import HotRoutes
from .housekeeping import freeze_start_up_objects, warm_up
from .registry import Registry
from .responses import GZIP_LEVEL
from .routers import docs, documents, health, items, search, stream, tiles, uploads, viewport
from .search import Searches
from .session import Streams
from .snapfile import SnapshotFiles
from .stores import Store, open_store
from .uploads import Uploads

__all__ = ["app", "create_app", "start_up"]

STATIC = Path(str(resources.files("app") / "static"))  # static/, packaged as app/static
FOLLOW_SECONDS = 0.05  # how often a process looks for what others wrote
log = logging.getLogger("vantage")
_started = False  # whether start_up() ran in this process (a forked worker inherits it)
app: FastAPI  # made on first use (the module's ``__getattr__``), not as the module is imported


def start_up() -> None:
    """This process's start-up, once (later calls do nothing): large blocks mapped on their
    own (``heap.map_large_blocks``), the kernels loaded or compiled before any request needs
    them (``housekeeping.warm_up``: a second from numba's cache, minutes without it), then
    what start-up made, compiled code included, left out of the collector's passes
    (``housekeeping.freeze_start_up_objects``, after the warm-up, before any request)."""
    global _started
    if _started:
        return
    map_large_blocks()
    warm_up()
    freeze_start_up_objects()
    _started = True


def __getattr__(name: str) -> FastAPI:
    """``app``: the app for the process's settings, made after the process's start-up the
    first time it is asked for, then kept (``uvicorn app.main:app`` asks once, as it loads)."""
    if name != "app":
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    try:
        start_up()
        made = create_app(get_settings())
    except AttributeError as error:  # a bug while making it, not "no attribute app": said as one
        raise RuntimeError(f"making app.main's app failed: {error!r}") from error
    globals()["app"] = made
    return made


def create_app(settings: Settings) -> FastAPI:
    """The app for ``settings``: routers, error translation, the door's middleware and the
    fast path are assembled now; the store, the registry and the background upkeep are made
    as its lifespan starts (after the process's start-up, if nothing ran it yet)."""

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        start_up()  # done already when ``app`` was loaded: nothing then
        store = open_store(settings.data_dir, settings.database_url)  # opens no document: on demand
        files = SnapshotFiles(
            settings.data_dir / "snapshots", settings.import_bytes, settings.frames_mb << 20
        )
        app.state.registry = registry = Registry(
            store, files, settings.cache_bytes, settings.max_documents, settings.tile_cache_mb << 20
        )
        log.info(
            "documents open on demand within a cache of %d MB (VANTAGE_CACHE_MB)", settings.cache_bytes >> 20
        )
        loop, woken = asyncio.get_running_loop(), asyncio.Event()
        store.on_change = lambda: loop.call_soon_threadsafe(woken.set)  # PostgreSQL's NOTIFY
        app.state.searches = Searches(settings.search_threads, settings.search_queue)  # per worker
        follower = loop.create_task(_follow(registry, woken, settings.save_edits_seconds))
        sweeping = loop.create_task(_sweep(files, store, app.state.uploads))
        yield
        await sweeping
        follower.cancel()
        await app.state.compactions.finished()  # those under way; none starts now
        await registry.settle()
        app.state.searches.pool.shutdown(cancel_futures=True)
        store.close()

    app = FastAPIOffline(  # /docs and /redoc (routers.docs) from packaged assets: no internet needed
        docs_url=None,
        redoc_url=None,
        title="Vantage",
        summary="Viewport virtualisation for large document canvases.",
        description="**WebSocket** `/documents/{doc}/stream`: " + (stream.__doc__ or ""),
        lifespan=lifespan,
        # On, FastAPI's telemetry looks up OpenTelemetry's providers on every request (~2.4 us,
        # 3% of a viewport's): off, that look is skipped along with the spans.
        telemetry=None if settings.telemetry else {"tracing": False, "metrics": False, "logs": False},
    )
    app.state.settings = settings
    app.state.streams = Streams(settings.max_streams, settings.stream_unread_mb << 20)
    app.state.import_turns = asyncio.Semaphore(settings.max_imports)
    app.state.compactions = Compactions()
    app.state.uploads = Uploads(settings.data_dir / "uploads", settings.max_upload_bytes)
    for module in (health, docs, documents, uploads, items, viewport, tiles, search, stream):
        app.include_router(module.router)
    app.mount("/static", StaticFiles(directory=STATIC), name="static")
    # starlette types a handler as taking any Exception, not the class it is registered for
    app.add_exception_handler(ServiceError, _service_error)  # type: ignore[arg-type]
    if settings.gzip_min_bytes is not None:  # innermost: compresses what the routes answer
        # Small answers go as they are; see responses.GZIP_LEVEL for the level.
        app.add_middleware(GZipMiddleware, minimum_size=settings.gzip_min_bytes, compresslevel=GZIP_LEVEL)
    # Then CORS answers preflights, and the guard sees every request.
    app.state.access = access = Access(settings)
    app.add_middleware(Guard, settings=settings, access=access)
    if settings.origins:
        # Tokens travel in a header, not cookies: no credentials, so "*" never meets them.
        app.add_middleware(
            CORSMiddleware,
            allow_origins=settings.origins,
            allow_credentials=False,
            allow_methods=["GET", "POST", "PUT", "PATCH", "DELETE"],
            allow_headers=["Authorization", "Content-Type", "If-None-Match"],  # a tile revalidated
            expose_headers=["ETag"],
        )

    @app.get("/", include_in_schema=False)
    async def read_page() -> FileResponse:
        """The canvas page: pan and zoom a document (plain JS in ``static/``, no build step)."""
        return FileResponse(STATIC / "index.html")

    for name in ("uvicorn.access", "uvicorn.error"):  # the second logs each stream's URL
        logging.getLogger(name).addFilter(_hide_tokens)
    # Around the whole stack, built now: plainly valid viewport and diff requests are answered
    # as the stack would answer them but without its per-request work (FastAPI's error,
    # telemetry and body-limit layers wrap every send); the rest go on to the stack. FastAPI's
    # own spans, made before the stack, still cover them.
    app.middleware_stack = HotRoutes(app.build_middleware_stack(), app.state, viewport.HOT, tile_answered)
    return app


async def _follow(registry: Registry, woken: asyncio.Event, save_edits_seconds: float) -> None:
    """Catch open documents up with what other processes write, so their streams get pushes
    within FOLLOW_SECONDS even when no request comes (a request catches up by itself), or at
    once when the store says something changed; and save the edits of each open document
    ``save_edits_seconds`` after the first not saved yet, even when no edit comes after it."""
    while True:
        with contextlib.suppress(TimeoutError):
            await asyncio.wait_for(woken.wait(), FOLLOW_SECONDS)
        woken.clear()
        registry.save_old_edits(save_edits_seconds)
        try:
            await registry.refresh()
        except Exception:  # a store error now is a store error next time: log, keep following
            log.exception("catching up with the store failed")


async def _sweep(files: SnapshotFiles, store: Store, uploads: Uploads) -> None:
    """Remove snapshot files and store rows no document's base needs, and uploads long
    untouched, off the event loop, after start-up."""
    try:
        await run_in_threadpool(files.sweep, store)
        await run_in_threadpool(store.sweep_rows)
        await run_in_threadpool(uploads.sweep)
    except Exception:  # a cache's upkeep: the store away now is not a reason to stop serving
        log.exception("sweeping the snapshot files, rows and uploads failed")


async def _service_error(request: Request, error: ServiceError) -> JSONResponse:
    return JSONResponse({"detail": error.message}, status_code=error.status, headers=error.headers or None)


_PARAMETER = re.compile(r"(?<=[?&])([^=&#\s]*)=([^&#\s]*)")


def _hide_tokens(record: logging.LogRecord) -> bool:
    """The log never shows a ``?token=``, however its name is spelled (``%74oken`` is ``token``
    too, to the server that reads it)."""
    if isinstance(record.args, tuple):
        record.args = tuple(_PARAMETER.sub(_hidden, a) if isinstance(a, str) else a for a in record.args)
    return True


def _hidden(parameter: re.Match[str]) -> str:
    name = parameter[1]
    return f"{name}=***" if unquote_plus(name) == "token" else parameter[0]
