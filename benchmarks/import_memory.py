"""How much memory an import costs the server, against the size of its body.

Seeded: writes the long document (``--pages`` pages) as NDJSON, starts Vantage, imports it
into an empty document and then again into the same (the upsert path, which merges with what
is stored), sampling the server's RSS every 10 ms. Prints the peak growth over the idle RSS
as a multiple of the body's size: what ``VANTAGE_MAX_BODY_BYTES`` implies in memory.

    python -m benchmarks.import_memory --pages 2000
"""

import argparse
import tempfile
import threading
import time
from pathlib import Path

from app.demo import ndjson_lines
from benchmarks.servers import Server, vantage_server
from benchmarks.service_bench import import_scene
from spatial import scenes


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--pages", type=int, default=2000, help="pages of the long document (2000: ~1M items)"
    )
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    with tempfile.TemporaryDirectory(prefix="vantage-import-memory-") as work:
        work = Path(work)
        boxes, kinds = scenes.long_document(pages=args.pages, seed=args.seed)
        body = work / "scene.ndjson"
        with open(body, "wb") as out:
            out.writelines(ndjson_lines(boxes, kinds))
        size = body.stat().st_size
        print(f"{len(boxes):,} items, body {size / 2**20:.1f} MiB")
        with vantage_server("vantage", {"VANTAGE_DATA_DIR": str(work / "data")}, work) as server:
            server.start().wait_ready()
            for label in ("into an empty document", "again, into the same"):
                idle = server.rss()
                peak, done = [idle], threading.Event()

                def sample() -> None:
                    while not done.is_set():
                        peak[0] = max(peak[0], server.rss())
                        time.sleep(0.01)

                sampler = threading.Thread(target=sample)
                sampler.start()
                try:
                    _, seconds = (
                        import_scene(server, body, len(boxes))
                        if label.startswith("into")
                        else (None, _reimport(server, body, len(boxes)))
                    )
                finally:
                    done.set()
                    sampler.join()
                growth = peak[0] - idle
                print(
                    f"import {label}: {seconds:.1f} s; RSS idle {idle / 2**20:.0f} MiB, peak +{growth / 2**20:.0f} MiB "
                    f"= {growth / size:.2f}x the body; after {server.rss() / 2**20:.0f} MiB"
                )


def _reimport(server: Server, body: Path, n: int) -> float:
    import httpx

    with httpx.Client(base_url=server.url, timeout=None) as client:
        doc = client.get("/documents").json()[0]["id"]
        with open(body, "rb") as data:
            started = time.perf_counter()
            answer = client.post(
                f"/documents/{doc}/items", content=data, headers={"content-type": "application/x-ndjson"}
            )
            answer.raise_for_status()
            return time.perf_counter() - started


if __name__ == "__main__":
    main()
