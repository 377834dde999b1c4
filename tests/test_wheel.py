"""The package as a user installs it: the checkout's wheel, installed into a fresh virtualenv (its
dependencies from the registry, as ``pip install`` takes them), gives a ``vantage serve`` that
serves the page, its client script and the API docs, run away from the checkout."""

import subprocess
import sys
import zipfile

import httpx
import pytest
from service import ROOT

from app.launch import free_port, stop, wait_until_up

PAGE_FILES = ("index.html", "app.js", "app.css", "vantage-client.js", "policy.json", "favicon.svg")


# A fresh virtualenv's install, then its kernels compiled at the first start: past the 180 s that
# bounds other tests on a slow machine (its start alone may take 240 s, below)
@pytest.mark.timeout(600)
def test_the_wheel_installed_in_a_fresh_virtualenv_serves_the_page(tmp_path):
    dist, venv = tmp_path / "dist", tmp_path / "venv"
    _run(sys.executable, "-m", "pip", "wheel", "--quiet", "--no-deps", str(ROOT), "-w", str(dist))
    (wheel,) = dist.glob("*.whl")
    packaged = set(zipfile.ZipFile(wheel).namelist())
    assert {f"app/static/{name}" for name in PAGE_FILES} <= packaged

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
    port, away = free_port(), tmp_path / "elsewhere"  # not the checkout: only the wheel's files
    away.mkdir()
    server = subprocess.Popen(
        [str(venv / "bin" / "vantage"), "serve", "--port", str(port), "--workers", "1"],
        cwd=away,
        env={"PATH": "/usr/bin:/bin", "HOME": str(tmp_path), "VANTAGE_DATA_DIR": str(tmp_path / "data")},
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    url = f"http://127.0.0.1:{port}"
    try:
        wait_until_up(url, server, timeout=240)  # compiling the kernels of a new install: ~40 s
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


def _run(*command: str) -> None:
    done = subprocess.run(command, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, f"{' '.join(command)}:\n{done.stdout[-3000:]}\n{done.stderr[-3000:]}"
