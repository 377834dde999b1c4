"""The viewport server a user would write instead of Vantage, for service_bench to compare with.

FastAPI + a shapely 2 STRtree + orjson: on start-up it reads an NDJSON file of items (the same
lines Vantage imports), keeps them as dicts, and builds the tree over their boxes; a viewport
is ``tree.query(box, predicate="intersects")`` (exact, closed intervals: touching counts) and
the hits' dicts dumped with orjson. No store, no level of detail, no diff: the whole viewport
every time.

Run (the file path comes from the environment)::

    REFERENCE_NDJSON=/tmp/scene.ndjson python -m uvicorn benchmarks.reference_server:app \\
        --host 127.0.0.1 --port 8001 --no-access-log
"""

from __future__ import annotations

import os
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager

import numpy as np
import orjson
import shapely
from fastapi import FastAPI, Response

ENV = "REFERENCE_NDJSON"


def load(path: str) -> tuple[list[dict], shapely.STRtree]:
    """The items as parsed dicts, in file order, and an STRtree whose indices point into them."""
    with open(path, "rb") as f:
        items = [orjson.loads(line) for line in f if line.strip()]
    bounds = np.array([(it["x0"], it["y0"], it["x1"], it["y1"]) for it in items], dtype=np.float64)
    boxes = shapely.box(bounds[:, 0], bounds[:, 1], bounds[:, 2], bounds[:, 3])
    return items, shapely.STRtree(boxes)


@asynccontextmanager
async def lifespan(app: FastAPI) -> AsyncIterator[None]:
    app.state.items, app.state.tree = load(os.environ[ENV])
    yield


app = FastAPI(title="reference viewport server", lifespan=lifespan)


@app.get("/health")
def health() -> dict[str, str]:
    return {"status": "ok"}


@app.get("/viewport")
def viewport(x0: float, y0: float, x1: float, y1: float) -> Response:
    """Every item whose box touches the viewport, as a JSON list of item objects."""
    items = app.state.items
    hits = app.state.tree.query(shapely.box(x0, y0, x1, y1), predicate="intersects")
    return Response(orjson.dumps([items[i] for i in hits.tolist()]), media_type="application/json")
