import fcntl
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import built_wheel
import pytest
from hypothesis import HealthCheck, settings
from service import client, ndjson

from app.config import get_settings
from spatial import scenes

# The run's wheel build (``built_wheel.start``), if one was started
_WHEEL_BUILD = pytest.StashKey["subprocess.Popen | None"]()

# Two cores: keep example counts modest; CI gets the same profile.
settings.register_profile(
    "default", max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow]
)
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "default"))


def pytest_configure(config):
    """The index's kernels compiled (or loaded from numba's on-disk cache) before any test:
    after an install that takes minutes, which a test's own timeout would not allow (an app's
    start-up, in its lifespan, warms up). Run on several processes (``./test``: pytest-xdist's
    ``-n auto``), the controller compiles them before it starts its workers, which then load
    them from the cache: else each would compile them at once, on the same cores. The wheel
    that ``tests/test_wheel.py`` installs is built beside it, on the other core."""
    if hasattr(config, "workerinput") or config.option.collectonly:
        return  # a worker: the controller compiled them
    from app.housekeeping import warm_up

    config.stash[_WHEEL_BUILD] = built_wheel.start(config.args or config.getini("testpaths"))
    warm_up()


def pytest_unconfigure(config):
    built_wheel.stop(config.stash.get(_WHEEL_BUILD, None))


def pytest_collection_modifyitems(config, items):
    """On xdist's workers (which all collect, and must agree on the order), the modules go in
    the order of their cost, the costliest first, so that none is left to start last while
    the other workers wait for it: ``./test``'s scheduler (``--dist loadscope
    --no-loadscope-reorder``) hands a module's tests to one worker, in this order. A test
    marked ``slow(seconds=N)`` costs about N s, any other half a second."""
    if not hasattr(config, "workerinput"):
        return  # one process: the files' order

    def cost(item) -> float:
        slow = item.get_closest_marker("slow")
        return slow.kwargs.get("seconds", 10) if slow else 0.5

    modules: dict[str, float] = {}
    for item in items:
        module = item.nodeid.split("::")[0]
        modules[module] = modules.get(module, 0.0) + cost(item)
    items.sort(key=lambda item: -modules[item.nodeid.split("::")[0]])  # stable: a module's stay in order


@pytest.fixture(autouse=True)
def _settings_read_afresh():
    """The settings are read from the environment once, then cached: every test starts and
    ends with none cached, so an environment a test set (and undid) never outlives it."""
    get_settings.cache_clear()
    yield
    get_settings.cache_clear()


@pytest.fixture(autouse=True)
def _edits_folded_often(monkeypatch):
    """An overview folds its recent edits into arrays after a few entries here, not 2,048:
    every test's edits go through both, and the folds between them (in this process; a
    server started by a test folds at its own default)."""
    import spatial.overview._edits

    monkeypatch.setattr(spatial.overview._edits, "FOLD_AFTER", 5)


@pytest.fixture
def data_dir(tmp_path, monkeypatch):
    """A fresh, empty store for the service under test."""
    monkeypatch.setenv("VANTAGE_DATA_DIR", str(tmp_path))
    get_settings.cache_clear()
    return tmp_path


@pytest.fixture
def document(data_dir):
    """A client and a six-page document imported through the API: ``(client, doc id, boxes)``."""
    boxes, kinds = scenes.long_document(pages=6, seed=1)
    with client() as c:
        doc = c.post("/documents", json={"name": "report"}).json()
        answer = c.post(
            f"/documents/{doc['id']}/items",
            content=ndjson(boxes, kinds),
            headers={"content-type": "application/x-ndjson"},
        )
        assert answer.status_code == 200, answer.text
        assert answer.json() == {"imported": len(boxes), "version": 1}
        yield c, doc["id"], boxes


@pytest.fixture(scope="module", autouse=True)
def _browser_closed():
    """The Chromium a module's browser tests shared (``browser.chromium_page``), closed at its
    end: it is not kept running beside the next module's tests."""
    yield
    shared = sys.modules.get("browser")
    if shared is not None:
        shared.close_browser()


@pytest.fixture(scope="module")
def scratch_in_files():
    """Every scratch array in a file, however small (``app.packed.SCRATCH_IN_MEMORY``): for
    the modules that test the paths over mapped files on small inputs."""
    from app.packed import scratch_in_files

    with scratch_in_files():
        yield


@pytest.fixture(scope="session")
def memory_dir(tmp_path_factory):
    """A directory on a filesystem in memory (``/dev/shm``) where the machine has one, else
    in the run's temporary directory: for the tests that make thousands of tiny mapped
    scratch files, which ext4 takes ~0.4 ms each to free once written (a hundred times what
    making one costs). What they check is what the build writes, not the disk it is on."""
    shm = Path("/dev/shm")
    if not (shm.is_dir() and os.access(shm, os.W_OK)):
        yield tmp_path_factory.mktemp("memory")
        return
    directory = Path(tempfile.mkdtemp(prefix="vantage-test-", dir=shm))
    yield directory
    shutil.rmtree(directory, ignore_errors=True)


@pytest.fixture(scope="session")
def demo_data(tmp_path_factory, request):
    """The demo documents (a 2000-page report and a whiteboard, 1.3M items), made once a run
    by ``vantage demo``: ``(data directory, what the command printed)``."""
    if hasattr(request.config, "workerinput"):  # made once for all of xdist's workers
        data = tmp_path_factory.getbasetemp().parent / "demo-data"  # the run's, beside theirs
    else:
        data = tmp_path_factory.mktemp("demo-data")
    printed = data.with_name(f"{data.name}.printed")
    with open(f"{data}.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)  # another worker making them: wait for it
        if not printed.exists():
            command = [sys.executable, "-m", "app.cli", "demo", "--data-dir", str(data)]
            printed.write_text(subprocess.run(command, capture_output=True, text=True, check=True).stdout)
    return data, printed.read_text()


@pytest.fixture(scope="session")
def demo(demo_data):
    """A server of the demo documents (``demo_data``): ``(url, {name: document id})``."""
    import httpx
    from service import serving

    data, _ = demo_data
    with serving(data) as url:
        yield url, {d["name"]: d["id"] for d in httpx.get(f"{url}/documents").json()}


@pytest.fixture(scope="session")
def postgres(tmp_path_factory):
    """A real PostgreSQL server for the session (Debian's, run as an unprivileged user)."""
    from postgres import postgres_server

    with postgres_server(tmp_path_factory.mktemp("postgres")) as server:
        yield server


@pytest.fixture
def database_url(postgres):
    """The URL of a new, empty database on the session's PostgreSQL server."""
    import uuid

    return postgres.new_database(f"t_{uuid.uuid4().hex[:12]}")


@pytest.fixture(params=["sqlite", "postgresql"])
def open_store(request, tmp_path):
    """Opens a store of each engine, all on the same data (SQLite under ``tmp_path``, or a new
    PostgreSQL database): more than one is more than one process. Closed at the end."""
    from app.stores import open_store

    url = request.getfixturevalue("database_url") if request.param == "postgresql" else None
    opened = []

    def opener():
        opened.append(open_store(tmp_path / "data", url))
        return opened[-1]

    yield opener
    for store in opened:
        store.close()
