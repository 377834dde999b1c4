"""Debian's Chromium, driven by Playwright, for the browser tests.

Playwright's own browser builds are never downloaded: the tests launch the ``chromium``
package (``./test`` installs it on a fresh machine), or the binary ``VANTAGE_CHROMIUM`` names.

    from browser import ARTIFACTS, chromium_page

    def test_something():
        with chromium_page() as page:
            page.goto(url)
            page.screenshot(path=ARTIFACTS / "something.png")
"""

import os
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from playwright.sync_api import Browser, Page, Playwright, sync_playwright

#: Where tests save screenshots; ignored by git. ``page.screenshot(path=...)`` creates it.
ARTIFACTS = Path(__file__).parent / "artifacts"

DEFAULT_CHROMIUM = "/usr/bin/chromium"
FLAGS = (
    "--headless",
    "--no-sandbox",  # CI runs as root, where Chromium's sandbox refuses to start
    "--disable-gpu",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
)
VIEWPORT = {"width": 1280, "height": 800}


class ChromiumMissing(RuntimeError):
    """No Chromium binary where the browser tests look for one."""


def chromium_path() -> str:
    """The Chromium to launch: ``$VANTAGE_CHROMIUM``, else Debian's ``/usr/bin/chromium``."""
    path = os.environ.get("VANTAGE_CHROMIUM") or DEFAULT_CHROMIUM
    if not (os.path.isfile(path) and os.access(path, os.X_OK)):
        raise ChromiumMissing(
            f"no Chromium at {path}: the browser tests need Debian's chromium package "
            "(apt-get install chromium), or VANTAGE_CHROMIUM set to a Chromium binary"
        )
    return path


def artifact(name: str) -> Path:
    """A path in ``ARTIFACTS`` for a file a test writes, the folder created if need be."""
    ARTIFACTS.mkdir(parents=True, exist_ok=True)
    return ARTIFACTS / name


@contextmanager
def chromium_page(**context_options) -> Iterator[Page]:
    """A page in a fresh context of a headless Chromium, 1280x800; closed on exit.

    A context has a cache, cookies and local storage of its own, as a fresh profile has:
    nothing outlives one ``with`` block. The browser behind it is shared by a module's tests
    (``close_browser`` at its end, from ``conftest.py``): launching one with Playwright's
    driver took ~0.9 s, a context takes ~0.2. Keyword arguments go to Playwright's
    ``new_context`` (e.g. ``device_scale_factor=2``).
    """
    context = _browser().new_context(**({"viewport": VIEWPORT} | context_options))
    try:
        yield context.new_page()
    finally:
        context.close()


_shared: tuple[Playwright, Browser] | None = None  # this process's, while a module uses it


def _browser() -> Browser:
    global _shared
    if _shared is not None and not _shared[1].is_connected():  # it crashed: a new one
        close_browser()
    if _shared is None:
        playwright = sync_playwright().start()
        try:
            browser = playwright.chromium.launch(
                executable_path=chromium_path(), args=list(FLAGS), headless=True
            )
        except BaseException:
            playwright.stop()
            raise
        _shared = (playwright, browser)
    return _shared[1]


def close_browser() -> None:
    """Close the browser ``chromium_page`` shares, if one is running."""
    global _shared
    if _shared is None:
        return
    playwright, browser = _shared
    _shared = None
    try:
        browser.close()
    finally:
        playwright.stop()
