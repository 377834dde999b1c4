"""Liveness."""

from fastapi import APIRouter

from ..examples import answers

router = APIRouter(tags=["health"])


@router.get("/health", responses=answers(200, {"status": "ok"}))
def read_health() -> dict[str, str]:
    """Whether the service is up."""
    return {"status": "ok"}
