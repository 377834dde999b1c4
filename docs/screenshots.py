"""The README's pictures of the page, taken from the real page in Chromium.

Creates the demo documents in a temporary store (`vantage demo`), serves them (`vantage serve`),
opens the page on the 2000-page report in headless Chromium (Debian's, as the browser tests
use it) and saves two screenshots next to this file:

    page-zoomed-out.png   the report's first pages, 1/16 pixel a unit: words too small to draw
                          stand grouped in aggregates
    page-zoomed-in.png    page 5 at one pixel a unit: the words and their text

Run from the repository root (about half a minute; the store, ~650 MB, is removed after)::

    .venv/bin/python docs/screenshots.py
"""

from __future__ import annotations

import subprocess
import sys
import tempfile
from pathlib import Path

import httpx

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "tests"))  # browser.py: Chromium as the browser tests launch it

from browser import chromium_page  # noqa: E402

from app.launch import launch, stop  # noqa: E402

OUT = Path(__file__).resolve().parent
REPORT = "Demo: 2000-page report"
WINDOW = {"width": 960, "height": 720}
PAGE_5 = (306.0, 3600.0)  # the demo report's pages are 612 units wide, 816 apart
SHOTS = [("page-zoomed-out.png", 1 / 16), ("page-zoomed-in.png", 1.0)]  # name, pixels per unit

# The document is open and its first view answered: the page has placed its camera.
OPENED = "(doc) => { const s = window.vantage && window.vantage.state(); return !!s && s.doc === doc && s.synced; }"
# The frame on the canvas is drawn from the camera asked for and from the whole answer for it.
SETTLED = """(scale) => {
    const s = window.vantage && window.vantage.state();
    return !!s && s.synced && s.drawn && s.covered && s.scale === scale && s.goto.pending === 0 && s;
}"""


def shoot(page, path: Path, scale: float) -> str:
    """Centre the page on page 5 at ``scale``, wait until that frame is drawn, save it as
    ``path``; the status line it showed. Taken again if the page drew a new frame meanwhile."""
    page.evaluate(f"() => window.vantage.centreOn({PAGE_5[0]}, {PAGE_5[1]}, {scale})")
    for _ in range(5):
        state = page.wait_for_function(SETTLED, arg=scale, timeout=60_000).json_value()
        page.screenshot(path=path)
        after = page.evaluate("() => window.vantage.state()")
        if after["drawn"] and after["painted"] == state["painted"]:
            return state["status"]
    raise RuntimeError(f"the page kept drawing new frames while {path.name} was taken")


def main() -> None:
    with tempfile.TemporaryDirectory(prefix="vantage-screenshots-") as tmp:
        data = Path(tmp)
        subprocess.run([sys.executable, "-m", "app.cli", "demo", "--data-dir", str(data)], check=True)
        server, url = launch(data)
        try:
            docs = {d["name"]: d["id"] for d in httpx.get(f"{url}/documents").json()}
            with chromium_page(viewport=WINDOW) as page:
                page.goto(f"{url}/?doc={docs[REPORT]}")
                page.wait_for_function(OPENED, arg=docs[REPORT], timeout=60_000)
                for name, scale in SHOTS:
                    status = shoot(page, OUT / name, scale)
                    print(f"{OUT / name}: {status}")
        finally:
            stop(server)


if __name__ == "__main__":
    main()
