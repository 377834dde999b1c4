"""deploy/Dockerfile's image, built and started where a container engine runs (skipped, with the
reason, where none does): the container answers within seconds of its start, with the kernels
its wheel ships compiled, and keeps its documents in its volume."""

import shutil
import subprocess
import time
import uuid

import httpx
import pytest
from service import ROOT

from app.launch import free_port


def _engine() -> str:
    for engine in ("docker", "podman"):
        if shutil.which(engine) and subprocess.run([engine, "info"], capture_output=True).returncode == 0:
            return engine
    pytest.skip("no container engine runs here (docker info and podman info both failed)")


# Building the image installs the dependencies from the registry and compiles the kernels
@pytest.mark.slow(seconds=180)  # an image built: its dependencies installed, its kernels compiled
@pytest.mark.timeout(1200)
def test_the_image_answers_within_seconds_of_its_start_and_compiles_nothing(tmp_path):
    engine, tag = _engine(), f"vantage-test-{uuid.uuid4().hex[:8]}"
    built = subprocess.run(
        [engine, "build", "-f", str(ROOT / "deploy" / "Dockerfile"), "-t", tag, str(ROOT)],
        capture_output=True,
        text=True,
        timeout=1100,
    )
    assert built.returncode == 0, built.stderr[-3000:]
    port, name = free_port(), tag
    try:
        started = time.monotonic()
        subprocess.run(
            [
                engine,
                "run",
                "-d",
                "--name",
                name,
                "-p",
                f"127.0.0.1:{port}:8000",
                "-e",
                "VANTAGE_TOKENS=s3cret",
                tag,
            ],
            check=True,
            capture_output=True,
        )
        url, auth = f"http://127.0.0.1:{port}", {"Authorization": "Bearer s3cret"}
        while True:
            try:
                if httpx.get(f"{url}/health", timeout=2).status_code == 200:
                    break
            except httpx.TransportError:
                pass
            assert time.monotonic() - started < 60, "the container did not answer within 60 s"
            time.sleep(0.2)
        doc = httpx.post(f"{url}/documents", json={"name": "notes"}, headers=auth).json()
        items = "".join(f'{{"id":"n{i}","x0":{i},"y0":0,"x1":{i + 5},"y1":5}}\n' for i in range(1000))
        imported = httpx.post(
            f"{url}/documents/{doc['id']}/items",
            content=items,
            headers={**auth, "Content-Type": "application/x-ndjson"},
        )
        assert imported.status_code == 200, imported.text
        answer = httpx.get(
            f"{url}/documents/{doc['id']}/viewport", params={"x0": 0, "y0": 0, "x1": 10, "y1": 10}
        )
        assert answer.status_code == 200 and answer.json()["count"] == 11  # n0..n10 touch it
        said = subprocess.run([engine, "logs", name], capture_output=True, text=True)
        logs = said.stdout + said.stderr
        assert "Traceback" not in logs, logs
        assert "compil" not in logs, f"the image's kernels were compiled again:\n{logs}"
    finally:
        subprocess.run([engine, "rm", "-f", name], capture_output=True)
        subprocess.run([engine, "rmi", "-f", tag], capture_output=True)
