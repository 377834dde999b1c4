"""Start-up compiles every kernel a request uses: no request waits for numba to compile.

After an install, numba compiles each kernel once per argument types (seconds each), and a
request that meets a new combination waits for it, holding up every other request in its
worker (the first import once paid 8.6 s). The check runs in a fresh interpreter: start an
app (its lifespan runs the process's start-up, which compiles), count each kernel's compiled
signatures, then serve a realistic round of requests and look for any signature that appeared.
"""

import pickle

from service import in_fresh_interpreter

ROUND = r"""
import json, sys
import numpy as np
from fastapi.testclient import TestClient
from numba.core.dispatcher import Dispatcher

import app.main  # starts nothing: an app's lifespan (or loading app.main:app) compiles the kernels
from app import frames, looks, packed, search, table
from app.config import Settings
from app.demo import ndjson_lines
from spatial import _kernels, _walk, scenes


def signatures():
    return {
        f"{module.__name__}.{name}": len(kernel.signatures)
        for module in (_kernels, _walk, frames, looks, packed, search, table)
        for name, kernel in vars(module).items()
        if isinstance(kernel, Dispatcher)
    }


settings = Settings(data_dir=sys.argv[1], allowed_hosts="127.0.0.1,localhost,testserver")
with TestClient(app.main.create_app(settings), base_url="http://127.0.0.1") as client:
    before = signatures()  # once started up, before the first request
    boxes, kinds = scenes.long_document(pages=3, seed=0)
    doc = client.post("/documents", json={"name": "round"}).json()["id"]
    body = b"".join(ndjson_lines(boxes, kinds))
    client.post(f"/documents/{doc}/items", content=body, headers={"content-type": "application/x-ndjson"})
    view, moved, far = "0,0,1000,1000", "0,40,1000,1040", "0,0,100000,100000"
    requests = [
        ("get", f"/documents/{doc}/viewport?x0=0&y0=0&x1=1000&y1=1000", None),
        ("get", f"/documents/{doc}/viewport?x0=0&y0=0&x1=100000&y1=100000&scale=0.001&min_px=1", None),
        ("get", f"/documents/{doc}/diff?from={view}&to={moved}", None),
        ("get", f"/documents/{doc}/diff?from={far}&to={far}&scale=0.001&from_scale=0.002&min_px=1", None),
        ("get", f"/documents/{doc}/search?q=the", None),
        ("put", f"/documents/{doc}/items/new", {"x0": 1, "y0": 1, "x1": 5, "y1": 5, "kind": "word"}),
        ("patch", f"/documents/{doc}/items/new", {"x1": 7}),
        ("get", f"/documents/{doc}/viewport?x0=0&y0=0&x1=1000&y1=1000", None),
        ("get", f"/documents/{doc}/diff?from={view}&to={moved}&since=1", None),
        ("get", f"/documents/{doc}/search?q=the", None),
        ("delete", f"/documents/{doc}/items/new", None),
    ]
    # A document whose overview's cells span past 32 bits (a country's buildings, say)
    far = client.post("/documents", json={"name": "far"}).json()["id"]
    spread = [(0.0, 0.0), (2.0**41, 2.0**41), (2.0**41, 0.0), (7.0, 2.0**20)]
    body = b"".join(ndjson_lines(np.array([(x, y, x + 1.0, y + 1.0) for x, y in spread])))
    requests.append(("post", f"/documents/{far}/items", body))
    for method, url, payload in requests:
        answer = (
            client.request(method, url, content=payload, headers={"content-type": "application/x-ndjson"})
            if isinstance(payload, bytes)
            else client.request(method, url, json=payload)
        )
        assert answer.status_code in (200, 201), (method, url, answer.status_code, answer.text)
after = signatures()
print(json.dumps({name: after[name] - count for name, count in before.items() if after[name] > count}))
"""


def test_start_up_compiles_every_kernel_a_round_of_requests_uses(tmp_path):
    compiled = in_fresh_interpreter(ROUND, str(tmp_path / "data"), timeout=600)
    assert compiled == {}, f"compiled while serving, not at start-up: {compiled}"


LISTED = r"""
import json
from app import housekeeping

listed = housekeeping.Listed.here()
assert listed.path.exists(), "no list of the warm-up's kernels: the run's first warm-up writes it"
assert listed.load()

def signatures():  # of every compiled function of app and spatial, counted here
    import sys
    from numba.core.dispatcher import Dispatcher

    return {
        f"{module_name}.{name}": len(kernel.signatures)
        for module_name, module in list(sys.modules.items())
        if module_name.partition(".")[0] in ("app", "spatial")
        for name, kernel in list(vars(module).items())
        if isinstance(kernel, Dispatcher)
    }

before = signatures()
housekeeping._compile()  # the warm-up's work, which the list stands for
after = signatures()
print(json.dumps({name: n - before.get(name, 0) for name, n in after.items() if n > before.get(name, 0)}))
"""


def test_a_start_from_the_warm_ups_list_loads_every_kernel_its_work_calls():
    """A start loads the kernels the warm-up listed (``housekeeping.Listed``) instead of doing
    its work: then the work, done after, meets no kernel signature the list left out."""
    compiled = in_fresh_interpreter(LISTED, timeout=600)
    assert compiled == {}, f"the warm-up's work called these the list left out: {compiled}"


def test_a_list_of_kernels_missing_or_unreadable_is_the_work_to_do(tmp_path, caplog):
    """No list, a torn one or one naming a kernel this code lacks: ``load`` says so (the
    warm-up then does its work), the last two in the log."""
    from app.housekeeping import Listed

    assert not Listed(tmp_path / "none.kernels").load()
    (tmp_path / "torn.kernels").write_bytes(b"\x80\x05\x95 torn")
    assert not Listed(tmp_path / "torn.kernels").load()
    (tmp_path / "gone.kernels").write_bytes(pickle.dumps([("app.frames", "a_kernel_since_removed", ())]))
    assert not Listed(tmp_path / "gone.kernels").load()
    assert "cannot be used" in caplog.text
