"""The ASGI app, ``app.main:app``: assembles routers, nothing else."""

from fastapi import FastAPI

from .routers import health

app = FastAPI(title="Vantage", summary="Viewport virtualisation for large document canvases.")
app.include_router(health.router)
