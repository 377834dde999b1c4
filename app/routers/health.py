"""Liveness, and what this process holds."""

from fastapi import APIRouter, Request

from ..deps import RegistryDep
from ..examples import documented

__all__ = ["router"]

router = APIRouter(tags=["health"])


@router.get("/health", responses=documented(200, {"status": "ok", "store": "postgresql", "reachable": True}))
async def read_health(registry: RegistryDep) -> dict:
    """Whether the service is up, and its store reachable. ``degraded``: the store cannot be
    reached, so the documents open here answer reads as they stand, and writes and other
    documents answer 503 until it is back. Still 200: a load balancer should keep sending
    reads here."""
    # Here, not in the thread pool: under load the pool queues answers that take milliseconds
    # (zoomed out), and a probe waiting behind them would call a busy server dead. The check
    # is a read of the change log's head (SQLite), or what the listener last saw (PostgreSQL).
    store = registry.store.status()
    return {"status": "ok" if store["reachable"] else "degraded", **store}


@router.get(
    "/stats",
    responses=documented(
        200,
        {
            "worker": 4242,
            "open": 3,
            "held_bytes": 231_000_000,
            "budget_bytes": 6_000_000_000,
            "opens": 12,
            "hits": 51_377,
            "evictions": 9,
            "rebuilt": 0,
            "streams": 12,
            "unread_bytes": 0,
        },
    ),
)
async def read_stats(registry: RegistryDep, request: Request) -> dict:
    """This worker process's open documents: how many, the bytes they hold against the budget
    (VANTAGE_CACHE_MB), and how many opens, hits, evictions and snapshot rebuilds so far; its
    streams, and the bytes of their answers not yet taken by the clients
    (VANTAGE_STREAM_UNREAD_MB)."""
    streams = request.app.state.streams
    return {**registry.stats(), "streams": streams.open, "unread_bytes": streams.unread}
