"""The fast path for ``/viewport`` and ``/diff`` (``app.hot``) answers exactly as the
routes do: same status, headers and bytes, for valid queries and for every kind of invalid one
(which it hands to the routes), with and without gzip, with a token and CORS configured."""

import dataclasses
from typing import Annotated

import pytest
from fastapi import Query
from service import client

from app import hot
from app.config import get_settings
from app.routers import viewport

DIFF = "from=0,1000,700,1900&to=0,1060,700,1960"
VIEW = "x0=0&y0=1000&x1=700&y1=1900"
QUERIES = [
    f"diff?{DIFF}",
    f"diff?{DIFF}&scale=1&min_px=2",
    f"diff?{DIFF}&scale=0.05&min_px=4&limit=3",
    f"diff?{DIFF}&scale=1&min_px=2&from_scale=2&since=0",
    f"diff?{DIFF}&scale=0.05&min_px=4&from_band=1",
    f"diff?{DIFF}&from_band=1",  # 422 from the route: no level of detail
    f"diff?{DIFF}&since=99",  # 409
    f"diff?{DIFF}&since=-1",
    f"diff?{DIFF}&scale=0",
    f"diff?{DIFF}&scale=nan",
    f"diff?{DIFF}&scale=inf&min_px=1",
    f"diff?{DIFF}&min_px=-1",
    f"diff?{DIFF}&limit=0",
    f"diff?{DIFF}&limit=1.5",
    f"diff?{DIFF}&limit=",
    f"diff?{DIFF}&scale=1_0",
    f"diff?{DIFF}&scale=1&scale=2",
    f"diff?{DIFF}&unknown=1&token=x",
    "diff?from=0%2C1000%2C700%2C1900&to=0,1060,700,1960&scale=%2B1&min_px=+2",
    "diff?from=0,1000,700&to=0,1060,700,1960",
    "diff?from=0,1000,700,1900&to=a,b,c,d",
    "diff?from=0,1000,700,1900&to=0,1e999,700,1960",
    "diff?from=0,1000,700,1900",
    "diff",
    f"viewport?{VIEW}",
    f"viewport?{VIEW}&scale=0.05&min_px=4&limit=2",
    f"viewport?{VIEW}&scale=1e-3&min_px=1e3",
    "viewport?x0=0&y0=1000&x1=700",
    "viewport?x0=0&y0=1000&x1=700&y1=-5",
    "viewport?x0=0&y0=1000&x1=700&y1=abc",
    "viewport?x0=0&y0=1000&x1=700&y1=1e999",
    "viewport?x0=.5&y0=1000.&x1=7E2&y1=-0",
    *(
        f"viewport?x0={odd}&y0=1000&x1=700&y1=1900"
        for odd in ("1-2", "--1", ".", "-", "+-1", "1.2.3", "%2B.5")
    ),
    f"viewport?{VIEW}&limit=99999999999999999999",
    f"viewport?{VIEW}&limit=007",
    f"viewport?{VIEW}&scale=0.05&min_px=4&tiles=true",
    f"viewport?{VIEW}&scale=0.05&min_px=4&tiles=1",
    f"viewport?{VIEW}&scale=0.05&min_px=4&tiles=yes",  # pydantic's spelling: the route's
    f"viewport?{VIEW}&tiles=true",
    f"diff?{DIFF}&scale=0.05&min_px=4&tiles=true",
    f"diff?{DIFF}&scale=0.05&min_px=4&tiles=maybe",
]


def _both(c, path: str, headers: dict) -> tuple:
    """(fast, slow): the answer as served, and as served with the fast path turned off."""
    fast = c.get(path, headers=headers)
    original = hot.HotRoutes.answer

    async def never(self, scope, receive, send) -> bool:
        return False

    hot.HotRoutes.answer = never
    try:
        slow = c.get(path, headers=headers)
    finally:
        hot.HotRoutes.answer = original
    return fast, slow


@pytest.mark.parametrize("gzip", [False, True])
def test_the_fast_path_answers_as_the_routes_do(document, gzip):
    c, doc, _ = document
    headers = {"accept-encoding": "gzip" if gzip else "identity"}
    for query in [*QUERIES, *(q.replace("diff?", "cells?") for q in QUERIES[:2])]:
        fast, slow = _both(c, f"/documents/{doc}/{query}", headers)
        assert fast.status_code == slow.status_code, query
        assert fast.headers.multi_items() == slow.headers.multi_items(), query
        assert fast.content == slow.content, query
    fast, slow = _both(c, f"/documents/nope/{QUERIES[0]}", headers)
    assert (fast.status_code, fast.content) == (slow.status_code, slow.content) == (404, slow.content)


def test_the_fast_path_takes_valid_queries_and_leaves_the_rest(document):
    c, doc, _ = document
    taken = []
    original = viewport.diff_answer

    def counting(*args, **kwargs):
        taken.append(kwargs)
        return original(*args, **kwargs)

    routes = dict(viewport.HOT)
    viewport.HOT["diff"] = dataclasses.replace(routes["diff"], answer=counting)
    try:
        assert c.get(f"/documents/{doc}/diff?{DIFF}&scale=1&min_px=2&limit=5").status_code == 200
        assert taken == [
            {"from_": "0,1000,700,1900", "to": "0,1060,700,1960", "scale": 1.0, "min_px": 2.0, "limit": 5}
        ]
        assert c.get(f"/documents/{doc}/diff?{DIFF}&limit=0").status_code == 422
        assert len(taken) == 1  # the route validated it
    finally:
        viewport.HOT.update(routes)


def test_the_guard_and_cors_still_see_every_request(data_dir, monkeypatch):
    monkeypatch.setenv("VANTAGE_TOKENS", "secret")
    monkeypatch.setenv("VANTAGE_READ_TOKEN", "true")
    monkeypatch.setenv("VANTAGE_CORS_ORIGINS", "http://app.example")
    get_settings.cache_clear()
    auth = {"authorization": "Bearer secret"}
    with client() as c:
        doc = c.post("/documents", json={"name": "d"}, headers=auth).json()["id"]
        path = f"/documents/{doc}/viewport?{VIEW}"
        assert c.get(path).status_code == 401
        assert c.get(path, headers={"authorization": "Bearer wrong"}).status_code == 403
        assert c.get(path + "&token=secret").status_code == 200
        assert c.get(path, headers={**auth, "host": "evil.example"}).status_code == 400
        answer = c.get(path, headers={**auth, "origin": "http://app.example"})
        assert answer.status_code == 200
        assert answer.headers["access-control-allow-origin"] == "http://app.example"


def test_the_fast_path_takes_each_routes_parameters_from_its_declaration(data_dir):
    """Every query parameter the schema documents, and no other, with its requiredness."""
    with client() as c:
        paths = c.get("/openapi.json").json()["paths"]
    for name, route in viewport.HOT.items():
        declared = [p for p in paths[f"/documents/{{doc}}/{name}"]["get"]["parameters"] if p["in"] == "query"]
        assert set(route.converters) == {p["name"] for p in declared}, name
        assert route.required == {p["name"] for p in declared if p.get("required")}, name
    scale = viewport.HOT["diff"].converters["scale"][1]
    assert scale("0.5") == 0.5
    with pytest.raises(hot._Slow):
        scale("0")  # Query(gt=0), read from the declaration


def test_a_parameter_the_fast_path_cannot_check_is_refused_at_start_up():
    async def odd(x: Annotated[float, Query(multiple_of=2)]) -> None: ...

    with pytest.raises(TypeError, match="multiple_of"):
        hot.HotRoute.of(odd, lambda *a: b"")


def test_the_fast_path_serves_tiles_as_the_route_does(document, monkeypatch):
    c, doc, _ = document
    sheet = c.get(f"/documents/{doc}/viewport?{VIEW}&scale=0.02&min_px=1&tiles=true").json()
    band, z, (tx, ty, _, _) = sheet["tiles"]["band"], sheet["tiles"]["z"], sheet["tiles"]["range"]
    version = sheet["version"]
    tile = f"/documents/{doc}/tiles/{band}/{z}/{tx}/{ty}"
    etag = c.get(tile).headers["etag"]
    taken = []
    original = hot.HotRoutes.tile

    async def counting(self, *args) -> bool:
        taken.append(await original(self, *args))
        return taken[-1]

    monkeypatch.setattr(hot.HotRoutes, "tile", counting)
    cases = [
        (tile, {}),
        (tile, {"accept-encoding": "gzip"}),
        (f"{tile}?version={version}", {"accept-encoding": "gzip"}),
        (f"{tile}?version={version}&token=x", {}),
        (tile, {"if-none-match": etag}),
        (tile, {"if-none-match": f'"other", W/{etag}'}),
        (tile, {"if-none-match": "*"}),
        (f"{tile}?version={version + 5}", {}),  # the route waits, then 409s
        (f"{tile}?version=-1", {}),
        (f"{tile}?version=1&version=1", {}),
        (f"/documents/{doc}/tiles/99/{z}/0/0", {}),
        (f"/documents/{doc}/tiles/{band}/99999/0/0", {}),
        (f"/documents/{doc}/tiles/{band}/{z}/x/0", {}),
        (f"/documents/{doc}/tiles/{band}/{z}/0", {}),
        (f"/documents/nope/tiles/{band}/{z}/0/0", {}),
    ]
    for path, headers in cases:
        fast, slow = _both(c, path, headers)
        assert fast.status_code == slow.status_code, path
        assert fast.headers.multi_items() == slow.headers.multi_items(), path
        assert fast.content == slow.content, path
    assert taken.count(True) == 7  # the valid ones went the fast way; the rest, to the route
