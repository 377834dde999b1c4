"""The `vantage` command: help, demo documents, and a real server process answering on loopback."""

import os
import socket
import subprocess
import sys

import httpx
import numpy as np
import oracle
import pytest
from service import serving

from app.demo import DEMOS
from app.heap import huge_pages_on_request
from app.launch import free_port


def test_help_lists_the_commands():
    result = subprocess.run(
        [sys.executable, "-m", "app.cli", "--help"], capture_output=True, text=True, check=True
    )
    for command in ("serve", "demo", "import", "simulate"):
        assert command in result.stdout
    assert "`" not in result.stdout  # the description is prose, not the module's reST


def test_serve_starts_a_server_that_answers_health(tmp_path):
    with serving(tmp_path) as url:
        response = httpx.get(f"{url}/health")
        assert response.status_code == 200
        assert response.json() == {"status": "ok", "store": "sqlite", "reachable": True}


def test_serve_says_in_one_line_why_its_store_cannot_be_used(tmp_path):
    for url, said in (
        ("postgresql://vantage@127.0.0.1:1/vantage", "cannot reach PostgreSQL at VANTAGE_DATABASE_URL"),
        ("mysql://vantage@127.0.0.1/vantage", "VANTAGE_DATABASE_URL must be a postgresql:// URL"),
    ):
        result = subprocess.run(
            [sys.executable, "-m", "app.cli", "serve", "--port", str(free_port())],
            capture_output=True,
            text=True,
            timeout=60,
            env={**os.environ, "VANTAGE_DATA_DIR": str(tmp_path), "VANTAGE_DATABASE_URL": url},
        )
        assert result.returncode == 1 and said in result.stderr and "Traceback" not in result.stderr, result


def test_serve_refuses_a_port_in_use_or_a_bad_data_directory_in_one_line_announcing_no_url(tmp_path):
    (tmp_path / "a-file").write_text("not a directory")
    with socket.socket() as held:
        held.bind(("127.0.0.1", 0))
        held.listen()
        port = held.getsockname()[1]
        for data_dir, serve_on, said in (
            (
                tmp_path / "data",
                port,
                f"vantage serve: port {port} on 127.0.0.1 is in use: stop what holds it, ",
            ),
            (
                tmp_path / "a-file" / "data",
                free_port(),
                f"vantage serve: the data directory {tmp_path / 'a-file' / 'data'} cannot be used: ",
            ),
        ):
            result = subprocess.run(
                [
                    sys.executable,
                    "-m",
                    "app.cli",
                    "serve",
                    "--port",
                    str(serve_on),
                ],
                capture_output=True,
                text=True,
                timeout=60,
                env={**os.environ, "VANTAGE_DATA_DIR": str(data_dir)},
            )
            assert result.returncode == 1, result
            assert result.stderr.startswith(said) and result.stderr.count("\n") == 1, result.stderr
            assert "http://" not in result.stdout, result.stdout


def test_demo_creates_documents_worth_panning_that_the_server_serves(demo_data):
    data, printed = demo_data  # the run's `vantage demo --data-dir data`, made once for all
    assert any(line.startswith("created ") for line in printed.splitlines()), printed
    again = subprocess.run(
        [sys.executable, "-m", "app.cli", "demo", "--data-dir", str(data)],
        capture_output=True,
        text=True,
        check=True,
    )
    assert "already present" in again.stdout
    assert len(list((data / "snapshots").glob("*.vsnap"))) == len(DEMOS)  # made with their files
    with serving(data) as url:
        documents = {d["name"]: d for d in httpx.get(f"{url}/documents").json()}
        assert set(documents) == set(DEMOS) and sum(d["items"] for d in documents.values()) >= 1_000_000
        for name, make in DEMOS.items():
            boxes, _ = make()
            assert documents[name]["items"] == len(boxes)
            x0, y0 = boxes[len(boxes) // 2, :2]
            rect = (x0, y0, x0 + 1920, y0 + 1080)
            params = {**dict(zip(("x0", "y0", "x1", "y1"), rect, strict=True)), "limit": 100_000}
            body = httpx.get(
                f"{url}/documents/{documents[name]['id']}/viewport", params=params, timeout=60
            ).json()
            shown = np.array([[item[k] for k in ("x0", "y0", "x1", "y1")] for item in body["items"]])
            assert len(body["items"]) == body["count"] == oracle.hits(boxes, rect).sum() > 10
            assert sorted(map(tuple, shown.tolist())) == sorted(
                map(tuple, boxes[oracle.hits(boxes, rect)].tolist())
            )


def test_import_names_its_formats_and_exits_non_zero_naming_a_bad_file(tmp_path):
    shown = subprocess.run(
        [sys.executable, "-m", "app.cli", "import", "--help"], capture_output=True, text=True, check=True
    ).stdout
    for name in ("NDJSON", "CSV", "PDF", "Excalidraw", "tldraw", "--replace", "--columns", "--url"):
        assert name in shown
    bad = tmp_path / "bad.ndjson"
    bad.write_text('{"id": "a", "x0": 0, "y0": 0, "x1": 1, "y1": 1}\n{"id": "b", "x0": 2}\n')
    ran = subprocess.run(
        [sys.executable, "-m", "app.cli", "import", str(bad), "--data-dir", str(tmp_path / "data")],
        capture_output=True,
        text=True,
    )
    assert ran.returncode == 1
    assert f"vantage import: {bad}: line 2: Object missing required field `y0`" in ran.stderr


def test_a_local_import_names_its_store_and_creates_one_only_where_told(tmp_path):
    """Run from a directory no server reads, the default ./data is never made without a word."""
    (tmp_path / "a.ndjson").write_text('{"id": "a", "x0": 0, "y0": 0, "x1": 1, "y1": 1}\n')
    env = {k: v for k, v in os.environ.items() if k not in ("VANTAGE_DATA_DIR", "VANTAGE_DATABASE_URL")}

    def vantage_import(*args: str, **more: str) -> subprocess.CompletedProcess:
        command = [sys.executable, "-m", "app.cli", "import", "a.ndjson", *args]
        return subprocess.run(command, capture_output=True, text=True, cwd=tmp_path, env={**env, **more})

    refused = vantage_import()
    assert (refused.returncode, refused.stdout) == (2, "")
    assert refused.stderr == (
        f"vantage import: no store at {tmp_path}/data (the default, ./data, of the directory this runs in): "
        "to create one, say where with --data-dir DIR or VANTAGE_DATA_DIR (the directory a server reads), "
        "or import through a running server with --url\n"
    )
    assert not (tmp_path / "data").exists()
    created = vantage_import("--data-dir", "d")
    assert created.returncode == 0, created.stderr
    assert created.stderr.splitlines()[0] == (
        f"vantage import: into SQLite at {tmp_path}/d/vantage.sqlite3, a new store: it does not exist yet "
        f"and is created (a server reads it with VANTAGE_DATA_DIR={tmp_path}/d)"
    )
    again = vantage_import(VANTAGE_DATA_DIR="d")  # the same store, by the setting
    assert again.returncode == 0, again.stderr
    assert again.stderr.splitlines()[0] == f"vantage import: into SQLite at {tmp_path}/d/vantage.sqlite3"
    assert "1 items into 'a'" in again.stdout and "version 2" in again.stdout
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.ndjson", "d"]


# The program as ``vantage`` runs it (``main()``, its arguments its own), recording as it starts
# the tunable it was given and whether a block of heap its C library maps is in huge pages;
# its threshold set smaller (1 MiB), so the test's files stay small.
_STARTS = """
import ctypes, os, sys
libc = ctypes.CDLL("libc.so.6")
libc.malloc.restype = ctypes.c_void_p
block = libc.malloc(64 << 20)
ctypes.memset(block, 1, 64 << 20)
huge = next(int(l.split()[1]) for l in open("/proc/self/smaps_rollup") if l.startswith("AnonHugePages"))
with open(os.environ["STARTS"], "a") as out:
    out.write(f"{os.environ.get('GLIBC_TUNABLES')} {huge}\\n")
libc.free(ctypes.c_void_p(block))
sys.argv = ["vantage", *sys.argv[1:]]
import app.cli
app.cli.HUGE_PAGES_FROM = int(os.environ["HUGE_PAGES_FROM"])  # the mechanism, without 512 MiB files
app.cli.main()
"""


def test_a_large_local_import_runs_again_with_its_heap_in_huge_pages(tmp_path):
    if not huge_pages_on_request():
        pytest.skip("transparent huge pages are not given on request here (or not glibc 2.35+)")
    threshold = 1 << 20
    starts = tmp_path / "starts"
    env = {k: v for k, v in os.environ.items() if k != "GLIBC_TUNABLES"}
    env |= {"STARTS": str(starts), "HUGE_PAGES_FROM": str(threshold)}

    def imported(items: int, data: int, name: str) -> list[list[str]]:
        path = tmp_path / f"{name}.ndjson"
        with open(path, "w") as out:
            for i in range(items):
                out.write(
                    f'{{"id": "i{i}", "x0": {i}, "y0": 0, "x1": {i + 1}, "y1": 1, "data": {{"t": "{"x" * data}"}}}}\n'
                )
        command = [sys.executable, "-c", _STARTS, "import", str(path), "--doc", name]
        ran = subprocess.run(
            [*command, "--data-dir", str(tmp_path / name)], env=env, capture_output=True, text=True
        )
        assert ran.returncode == 0, ran.stderr
        assert f"{items:,} items into '{name}'" in ran.stdout
        said = [line.split() for line in starts.read_text().splitlines()]
        starts.unlink()
        return said

    # An import under the threshold starts once: starting again would cost more than it saves
    assert imported(threshold // 3900 - 10, 3800, "small") == [["None", "0"]]
    # One past it starts again at once, its heap in huge pages
    big = threshold // 3900 + 10
    (before, huge_before), (after, huge_after) = imported(big, 3800, "big")
    assert (before, after) == ("None", "glibc.malloc.hugetlb=1")
    assert int(huge_before) == 0 and int(huge_after) > 0  # kB: the block, some of it at least
    # Told to keep them off, it runs once: the operator's word stands
    env["GLIBC_TUNABLES"] = "glibc.malloc.hugetlb=0"
    assert imported(big, 3800, "off") == [["glibc.malloc.hugetlb=0", "0"]]
