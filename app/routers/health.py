"""Liveness."""

from fastapi import APIRouter

from ..examples import documented

router = APIRouter(tags=["health"])


@router.get("/health", responses=documented(200, {"status": "ok"}))
def read_health() -> dict[str, str]:
    """Whether the service is up."""
    return {"status": "ok"}
