"""The page fetches by the policy in ``static/policy.json``, the file the simulator reads
(``app/simulate/policy.py``): it declares none of those numbers itself, and a changed file
changes what a real page in Chromium asks for."""

import json
import re
from pathlib import Path

import httpx
import pytest
from browser import chromium_page
from service import NDJSON, ndjson, serving

from app.simulate.policy import POLICY
from spatial import scenes

STATIC = Path(__file__).resolve().parent.parent / "static"


def test_the_page_reads_every_field_of_the_policy_file_and_declares_none_itself():
    client = (STATIC / "vantage-client.js").read_text()  # the page's arithmetic lives in its client
    page = (STATIC / "app.js").read_text()
    assert "fetch(`${this.url}/static/policy.json`)" in client
    assert set(re.findall(r"\bpolicy\.(\w+)", client)) - {"json", "py"} == set(POLICY)
    assert 'from "./vantage-client.js"' in page
    assert not re.search(
        r"\bfetch\(|new WebSocket|XMLHttpRequest", page
    )  # only the client talks to the server
    for old in (
        "OVERSCAN",
        "REFETCH_AT",
        "LOD_STEP",
        "LOOKAHEAD_S",
        "SMOOTHING_S",
        "MIN_PX",
        "LIMIT",
        "POLL_MS",
    ):
        assert not re.search(rf"\b{old}\b", client + page), old


@pytest.fixture(scope="module")
def site(tmp_path_factory):
    """A served store with a 3-page document: ``(url, doc)``."""
    boxes, kinds = scenes.long_document(pages=3, seed=5)
    with serving(tmp_path_factory.mktemp("policy-data")) as url:
        doc = httpx.post(f"{url}/documents", json={"name": "report"}).json()["id"]
        answer = httpx.post(f"{url}/documents/{doc}/items", content=ndjson(boxes, kinds), headers=NDJSON)
        assert answer.status_code == 200, answer.text
        yield url, doc


def test_a_changed_policy_file_changes_what_the_page_asks_for(site):
    url, doc = site
    policy = {**POLICY, "overscan": 0.05, "minPx": 3, "limit": 7}
    assert policy != POLICY
    sent = []  # what the page sent on its stream
    with chromium_page() as page:
        page.on("websocket", lambda ws: ws.on("framesent", lambda payload: sent.append(json.loads(payload))))
        page.route("**/static/policy.json", lambda route: route.fulfill(json=policy))
        page.goto(f"{url}/?doc={doc}")
        page.wait_for_function("() => window.vantage && window.vantage.state().synced", timeout=15_000)
        state = page.evaluate("() => window.vantage.state()")
    assert state["transport"] == "ws"
    asked = [m for m in sent if "viewport" in m]
    assert asked and all(m["min_px"] == 3 and m["limit"] == 7 for m in asked)  # not 1 and 50,000
    assert state["requested"]["minPx"] == 3
    x0, y0, x1, y1 = state["viewport"]
    r = state["requested"]["rect"]
    # At rest (no look-ahead), the request is the screen plus the file's margin on each side,
    # grown out to the screen's pixel grid (so aggregates' masks fall on its pixels).
    pixel = 1 / state["scale"]
    assert abs(r[2] - r[0] - (x1 - x0) * (1 + 2 * 0.05)) < 2 * pixel
    assert abs(r[3] - r[1] - (y1 - y0) * (1 + 2 * 0.05)) < 2 * pixel
    for edge, screen_edge in ((r[0], x0), (r[1], y0), (r[2], x0), (r[3], y0)):
        assert (edge - screen_edge) / pixel == pytest.approx(round((edge - screen_edge) / pixel), abs=1e-6)
