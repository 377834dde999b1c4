"""Helpers for tests of the service: a client, NDJSON bodies, and the brute-force answers."""

import numpy as np
import orjson
from fastapi.testclient import TestClient

import oracle
from spatial import scenes


def client() -> TestClient:
    from app.main import app

    return TestClient(app)


def ndjson(boxes: np.ndarray, kinds=None) -> bytes:
    lines = []
    for i, (x0, y0, x1, y1) in enumerate(boxes.tolist()):
        item = {"id": f"i{i}", "x0": x0, "y0": y0, "x1": x1, "y1": y1, "z": i % 7}
        if kinds is not None:
            item["kind"] = scenes.KINDS[kinds[i]]
        lines.append(orjson.dumps(item))
    return b"\n".join(lines) + b"\n"


def ids_of(items) -> set[str]:
    return {item["id"] for item in items}


def expected(boxes: np.ndarray, rect, min_size: float = 0.0) -> set[str]:
    return {f"i{i}" for i in np.flatnonzero(oracle.hits(boxes, rect, min_size))}
