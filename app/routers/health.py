"""Liveness."""

from fastapi import APIRouter

router = APIRouter(tags=["health"])


@router.get("/health")
def read_health() -> dict[str, str]:
    """Whether the service is up."""
    return {"status": "ok"}
