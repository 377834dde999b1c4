"""The package as a user installs it: the checkout's wheel, installed into a fresh virtualenv (its
dependencies from the registry, as ``pip install`` takes them), gives a ``vantage import`` and a
``vantage serve`` that answer at once, with the kernels the wheel ships compiled (nothing
compiled after the install), and that serve the page, its client script and the API docs, run
away from the checkout."""

import subprocess
import sys
import zipfile

import built_wheel
import httpx
import pytest

from app.housekeeping import LISTED_SUFFIX
from app.launch import free_port, stop, wait_until_up

PAGE_FILES = ("index.html", "app.js", "app.css", "vantage-client.js", "policy.json", "favicon.svg")


# The wheel's build compiles its kernels (a minute or two; begun as the run began), then a
# fresh virtualenv's install: past the 180 s that bounds other tests on a slow machine
@pytest.mark.slow(seconds=40)  # the wheel installed; it was built beside the run's warm-up
@pytest.mark.timeout(900)
def test_the_wheel_installed_in_a_fresh_virtualenv_answers_at_once_and_serves_the_page(tmp_path):
    venv = tmp_path / "venv"
    wheel = built_wheel.wheel(tmp_path)  # built from the run's start (tests/built_wheel.py)
    assert wheel.name.endswith(f"-cp{sys.version_info.major}{sys.version_info.minor}-linux_x86_64.whl")
    packaged = set(zipfile.ZipFile(wheel).namelist())
    assert {f"app/static/{name}" for name in PAGE_FILES} <= packaged
    assert {"spatial/__pycache__", "app/__pycache__"} <= {
        name.rpartition("/")[0] for name in packaged if name.endswith(".nbi")
    }
    assert any(
        name.startswith("app/__pycache__/warm-up-") and name.endswith(LISTED_SUFFIX) for name in packaged
    )

    _run(getattr(sys, "_base_executable", sys.executable), "-m", "venv", str(venv))
    _run(
        str(venv / "bin" / "python"),
        "-m",
        "pip",
        "install",
        "--quiet",
        "--disable-pip-version-check",
        str(wheel),
    )
    installed = {path: path.stat().st_mtime_ns for path in venv.rglob("*.nb[ic]")}
    listed = {path: path.stat().st_mtime_ns for path in venv.rglob(f"*{LISTED_SUFFIX}")}
    port, away = free_port(), tmp_path / "elsewhere"  # not the checkout: only the wheel's files
    away.mkdir()
    # HOME: no user-wide cache of numba's to find kernels in, only the wheel's
    env = {"PATH": "/usr/bin:/bin", "HOME": str(tmp_path), "VANTAGE_DATA_DIR": str(tmp_path / "data")}
    items = away / "notes.csv"
    items.write_text(
        "id,x0,y0,x1,y1\n" + "".join(f"n{i},{i},{i % 97},{i + 5},{i % 97 + 5}\n" for i in range(10_000))
    )
    imported = subprocess.run(
        [str(venv / "bin" / "vantage"), "import", str(items), "--data-dir", env["VANTAGE_DATA_DIR"]],
        cwd=away,
        env=env,
        capture_output=True,
        text=True,
        timeout=60,  # ~1.3 s here; a compile took 112 s
    )
    assert imported.returncode == 0, imported.stderr
    server = subprocess.Popen(
        [str(venv / "bin" / "vantage"), "serve", "--port", str(port), "--workers", "1"],
        cwd=away,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    url = f"http://127.0.0.1:{port}"
    try:
        wait_until_up(url, server, timeout=60)  # ~2 s here; a compile took 30 s more
        (doc,) = httpx.get(f"{url}/documents").json()
        answer = httpx.get(
            f"{url}/documents/{doc['id']}/viewport", params={"x0": 0, "y0": 0, "x1": 100, "y1": 100}
        )
        assert answer.status_code == 200 and answer.json()["count"] == 101  # n0..n100 touch it
        page = httpx.get(f"{url}/")
        assert page.status_code == 200 and "/static/app.js" in page.text
        for name in PAGE_FILES:
            assert httpx.get(f"{url}/static/{name}").status_code == 200, name
        assert httpx.get(f"{url}/docs").status_code == 200
        assert httpx.get(f"{url}/openapi.json").json()["info"]["title"] == "Vantage"
    finally:
        stop(server, timeout=15)
        said = server.communicate()[0]
        print(said)  # shown when the test fails
    assert "Traceback" not in said, said
    assert "compil" not in imported.stderr + said, "the wheel's kernels were compiled again"
    # numba writes a kernel it compiles to its cache: none new, none rewritten
    assert {path: path.stat().st_mtime_ns for path in venv.rglob("*.nb[ic]")} == installed
    # the warm-up's list the wheel ships is this code's: loaded, not made again by the work
    assert {path: path.stat().st_mtime_ns for path in venv.rglob(f"*{LISTED_SUFFIX}")} == listed


def _run(*command: str) -> None:
    done = subprocess.run(command, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, f"{' '.join(command)}:\n{done.stdout[-3000:]}\n{done.stderr[-3000:]}"
