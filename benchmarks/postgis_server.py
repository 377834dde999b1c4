"""The viewport server a user would write on PostGIS instead of Vantage, for service_bench.

FastAPI + psycopg 3 (a psycopg_pool ConnectionPool) + orjson over one PostGIS table: the items'
fields as columns and ``box``, a geometry made from the corners, under a GiST index. A viewport
is the standard bounding-box idiom, ``box && ST_MakeEnvelope(x0, y0, x1, y1)``, answered whole
every time as a JSON list of item objects (id, x0, y0, x1, y1, kind, z: the fields Vantage
answers), at most ``limit`` of them. No level of detail, no diff.

PostgreSQL writes the JSON itself (``row_to_json``, joined with commas: as compact as orjson's)
and the route passes the text on: under service_bench's load that served 1.5-2x the requests
of fetching rows into Python and dumping them with orjson, which ``POSTGIS_JSON=python`` selects.

``&&`` compares the boxes PostGIS keeps in single precision, rounded outwards, so it may also
return items that miss the viewport by a rounding step; the same rows are checked again on their
double columns (closed intervals: touching counts), which costs nothing once the rows are read,
so the answer is exact, as the other servers' are.

Load a scene (the NDJSON lines Vantage imports), then serve it::

    python -m benchmarks.postgis_server load postgresql://user@host:5432/db /tmp/scene.ndjson
    POSTGIS_URL=postgresql://user@host:5432/db python -m uvicorn benchmarks.postgis_server:app \\
        --host 127.0.0.1 --port 8003 --no-access-log
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from pathlib import Path

import orjson
import psycopg
from fastapi import FastAPI, Response
from psycopg_pool import ConnectionPool

ENV_URL = "POSTGIS_URL"
ENV_POOL = "POSTGIS_POOL"  # connections the pool may hold (default 8: service_bench's panners)
ENV_JSON = "POSTGIS_JSON"  # "sql" (default): PostgreSQL writes the JSON; "python": orjson does
TABLE = "items"
COLUMNS = ("id", "x0", "y0", "x1", "y1", "kind", "z")
MAX_LIMIT = 100_000  # Vantage's most items per answer, so every server answers alike

SCHEMA = f"""
CREATE EXTENSION IF NOT EXISTS postgis;
DROP TABLE IF EXISTS {TABLE};
CREATE TABLE {TABLE} (
    id text PRIMARY KEY,
    x0 double precision NOT NULL, y0 double precision NOT NULL,
    x1 double precision NOT NULL, y1 double precision NOT NULL,
    kind text,
    z integer NOT NULL DEFAULT 0,
    -- made by PostgreSQL from the corners as COPY stores each row
    box geometry GENERATED ALWAYS AS (ST_MakeEnvelope(x0, y0, x1, y1)) STORED
)
"""
# `&&` picks the candidates through the index; the double columns keep those that truly touch
QUERY = f"""
SELECT {", ".join(COLUMNS)} FROM {TABLE}
WHERE box && ST_MakeEnvelope(%(x0)s, %(y0)s, %(x1)s, %(y1)s)
  AND x0 <= %(x1)s AND x1 >= %(x0)s AND y0 <= %(y1)s AND y1 >= %(y0)s
LIMIT %(limit)s
"""
QUERY_JSON = f"SELECT coalesce('[' || string_agg(row_to_json(t)::text, ',') || ']', '[]') FROM ({QUERY}) t"


def load(url: str, ndjson: Path) -> dict[str, float]:
    """(Re)create the table from an NDJSON file: COPY the rows, build the GiST index, ANALYZE.

    Returns the seconds of each step and the table's size: ``rows``, ``copy_s``, ``index_s``,
    ``analyze_s``, ``table_bytes``, ``index_bytes``.
    """
    timings: dict[str, float] = {}
    with psycopg.connect(url, autocommit=True) as db:
        db.execute(SCHEMA)
        t0 = time.perf_counter()
        rows = 0
        copying = f"COPY {TABLE} ({', '.join(COLUMNS)}) FROM STDIN"
        with db.transaction(), db.cursor().copy(copying) as copy, open(ndjson, "rb") as f:
            for line in f:
                if not line.strip():
                    continue
                it = orjson.loads(line)
                copy.write_row(
                    (it["id"], it["x0"], it["y0"], it["x1"], it["y1"], it.get("kind"), it.get("z", 0))
                )
                rows += 1
        timings["copy_s"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        db.execute(f"CREATE INDEX {TABLE}_box ON {TABLE} USING gist (box)")
        timings["index_s"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        db.execute(f"ANALYZE {TABLE}")
        timings["analyze_s"] = time.perf_counter() - t0
        timings["rows"] = rows
        timings["table_bytes"] = db.execute(f"SELECT pg_table_size('{TABLE}')").fetchone()[0]
        timings["index_bytes"] = db.execute(f"SELECT pg_indexes_size('{TABLE}')").fetchone()[0]
    return timings


@asynccontextmanager
async def lifespan(app: FastAPI) -> AsyncIterator[None]:
    size = int(os.environ.get(ENV_POOL, "8"))
    # Prepared on each connection by psycopg after a few uses: the plan is made once, not per request
    with ConnectionPool(
        os.environ[ENV_URL], min_size=size, max_size=size, kwargs={"autocommit": True}, open=True
    ) as pool:
        pool.wait()
        app.state.pool = pool
        app.state.sql_json = os.environ.get(ENV_JSON, "sql") != "python"
        yield


app = FastAPI(title="PostGIS viewport server", lifespan=lifespan)


@app.get("/health")
def health() -> dict[str, str]:
    with app.state.pool.connection() as db:
        db.execute("SELECT 1")
    return {"status": "ok"}


@app.get("/viewport")
def viewport(x0: float, y0: float, x1: float, y1: float, limit: int = MAX_LIMIT) -> Response:
    """Every item whose box touches the viewport (at most ``limit``), as a JSON list of objects."""
    params = {"x0": x0, "y0": y0, "x1": x1, "y1": y1, "limit": max(0, min(limit, MAX_LIMIT))}
    with app.state.pool.connection() as db:
        if app.state.sql_json:
            body = db.execute(QUERY_JSON, params).fetchone()[0]
        else:
            rows = db.execute(QUERY, params).fetchall()
            body = orjson.dumps([dict(zip(COLUMNS, row, strict=True)) for row in rows])
    return Response(body, media_type="application/json")


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.postgis_server", description=__doc__)
    commands = parser.add_subparsers(dest="command", required=True)
    loading = commands.add_parser("load", help="(re)create the items table from an NDJSON file")
    loading.add_argument("url", help="postgresql://... of a database where CREATE EXTENSION postgis works")
    loading.add_argument("ndjson", type=Path)
    args = parser.parse_args(argv)
    timings = load(args.url, args.ndjson)
    sys.stdout.write(orjson.dumps(timings).decode() + "\n")


if __name__ == "__main__":
    main()
