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
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from playwright.sync_api import Page, sync_playwright

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
    """A page in a headless Chromium with a fresh profile, 1280x800; closed on exit.

    The profile is a new temporary user data dir, removed afterwards, so no cache, cookie or
    local storage outlives one ``with`` block. Keyword arguments go to Playwright's
    ``launch_persistent_context`` (e.g. ``device_scale_factor=2``).
    """
    executable = chromium_path()
    with (
        tempfile.TemporaryDirectory(prefix="vantage-chromium-", ignore_cleanup_errors=True) as profile,
        sync_playwright() as playwright,
    ):
        options = {"viewport": VIEWPORT} | context_options
        context = playwright.chromium.launch_persistent_context(
            profile, executable_path=executable, args=list(FLAGS), headless=True, **options
        )
        try:
            yield context.pages[0] if context.pages else context.new_page()
        finally:
            context.close()
