"""The heaviest panning load for 60 s against a real server while imports and edits land:
zero errors, every sampled answer equal to brute force, memory flat. Opt in: ./test -m load."""

import json
import subprocess
import sys
import threading
import time

import httpx
import numpy as np
import oracle
import pytest
from service import NDJSON, ndjson, spawn_server

from spatial import scenes

SECONDS = 60


def _rss_mb(pid: int) -> float:
    with open(f"/proc/{pid}/status") as f:
        return next(int(line.split()[1]) for line in f if line.startswith("VmRSS")) / 1024


@pytest.mark.load
@pytest.mark.timeout(600)
def test_sixty_seconds_of_the_heaviest_load_with_writes(tmp_path):
    boxes, kinds = scenes.long_document(pages=200, seed=9)
    server, url = spawn_server(tmp_path / "data")
    failures: list[str] = []
    checked = 0
    try:
        doc = httpx.post(f"{url}/documents", json={"name": "loaded"}).json()["id"]
        body = ndjson(boxes, kinds)
        httpx.post(
            f"{url}/documents/{doc}/items", content=body, timeout=120, headers=NDJSON
        ).raise_for_status()
        rss_before = _rss_mb(server.pid)
        done = threading.Event()

        def write() -> None:  # re-imports of the same items, and edits far from them
            k = 0
            with httpx.Client(base_url=url, timeout=60) as c:
                while not done.is_set():
                    k += 1
                    if k % 50 == 0:
                        answer = c.post(f"/documents/{doc}/items", content=body, headers=NDJSON)
                    else:
                        far = {"x0": 1e6 + k % 200, "y0": 1e6, "x1": 1e6 + k % 200 + 5, "y1": 1e6 + 5}
                        answer = c.put(f"/documents/{doc}/items/far{k % 100}", json=far)
                    if answer.status_code not in (200, 201):
                        failures.append(f"write: {answer.status_code} {answer.text[:200]}")
                    time.sleep(0.02)

        def check() -> None:  # sampled answers against brute force over the unchanging items
            nonlocal checked
            rng = np.random.default_rng(1)
            with httpx.Client(base_url=url, timeout=60) as c:
                while not done.is_set():
                    x, y = boxes[rng.integers(len(boxes)), :2]
                    rect = (float(x) - 300, float(y) - 400, float(x) + 900, float(y) + 800)
                    params = {**dict(zip(("x0", "y0", "x1", "y1"), rect, strict=True)), "limit": 100_000}
                    items = c.get(f"/documents/{doc}/viewport", params=params).json()["items"]
                    truth = {f"i{i}" for i in np.flatnonzero(oracle.hits(boxes, rect))}
                    if {item["id"] for item in items} != truth:
                        failures.append(f"wrong answer for {rect}")
                    checked += 1
                    time.sleep(0.05)

        helpers = [threading.Thread(target=write), threading.Thread(target=check)]
        for t in helpers:
            t.start()
        simulate = subprocess.run(
            [
                sys.executable,
                "-m",
                "app.simulate",
                "--url",
                url,
                "--doc",
                doc,
                "--modes",
                "stream",
                "--overscan",
                "0",
                "--lod",
                "off",
                "--users",
                "8",
                "--seconds",
                str(SECONDS),
                "--out",
                str(tmp_path / "sim"),
            ],
            capture_output=True,
            text=True,
            timeout=SECONDS + 120,
        )
        done.set()
        for t in helpers:
            t.join()
        assert simulate.returncode == 0, simulate.stderr[-2000:]
        (result,) = json.loads((tmp_path / "sim" / "result.json").read_text())["modes"]
        rss_after = _rss_mb(server.pid)
        print(
            f"\nload: {result['requests']} stream answers ({result['requests_per_s']:.0f}/s), "
            f"p99 {result['latency_ms']['p99']:.1f} ms, {checked} answers checked, "
            f"RSS {rss_before:.0f} -> {rss_after:.0f} MB"
        )
        assert result["errors"] == 0 and result["requests"] > 1000
        assert not failures, failures[:5]
        assert checked > 100
        assert rss_after < rss_before * 1.25 + 50  # flat: no growth with requests served
    finally:
        server.terminate()
        server.communicate(timeout=10)
