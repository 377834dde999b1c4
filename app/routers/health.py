"""Liveness, and what this process holds."""

from fastapi import APIRouter

from ..deps import RegistryDep
from ..examples import documented

router = APIRouter(tags=["health"])


@router.get("/health", responses=documented(200, {"status": "ok"}))
def read_health() -> dict[str, str]:
    """Whether the service is up."""
    return {"status": "ok"}


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
        },
    ),
)
async def read_stats(registry: RegistryDep) -> dict:
    """This worker process's open documents: how many, the bytes they hold against the budget
    (VANTAGE_CACHE_MB), and how many opens, hits, evictions and snapshot rebuilds so far."""
    return registry.stats()
