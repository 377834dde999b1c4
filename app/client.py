"""A small Python client of a Vantage server (httpx), and ``launch``, which starts one.

The simulator, the benchmarks and the tests start servers and talk to them through this
module rather than each on its own::

    process, url = launch(Path("data"), "--log-level", "info")
    with Client(url) as vantage:
        doc = vantage.create_document("report")["id"]
        vantage.import_items(doc, open("report.ndjson", "rb"))
        vantage.viewport(doc, (0, 0, 1920, 1080), scale=0.5, min_px=1)

It needs httpx, which the ``simulate`` and ``dev`` extras install.
"""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
import time
from collections.abc import Iterable
from pathlib import Path
from typing import IO, Any

import httpx

__all__ = ["Client", "free_port", "launch", "wait_until_up"]

NDJSON = {"content-type": "application/x-ndjson"}


def free_port() -> int:
    """A TCP port on loopback that nothing listens on now."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def wait_until_up(
    url: str, process: subprocess.Popen | None = None, timeout: float = 120.0, path: str = "/health"
) -> None:
    """Until ``url + path`` answers 200.

    :raises RuntimeError: if ``process`` exits first, or after ``timeout`` seconds
    """
    deadline = time.monotonic() + timeout
    with httpx.Client(timeout=5.0) as client:
        while True:
            if process is not None and process.poll() is not None:
                raise RuntimeError(
                    f"the server at {url} exited with code {process.returncode} before it answered"
                )
            try:
                if client.get(url + path).status_code == 200:
                    return
            except httpx.TransportError:
                pass
            if time.monotonic() > deadline:
                raise RuntimeError(f"the server at {url} did not answer {path} within {timeout:g} s")
            time.sleep(0.02)


def launch(
    data_dir: Path, *args: str, env: dict[str, str] | None = None, output: int | IO[Any] = subprocess.PIPE
) -> tuple[subprocess.Popen, str]:
    """``vantage serve`` on a free loopback port with its store in ``data_dir`` and ``args``
    passed on (one worker, the process itself, unless ``args`` say ``--workers``), once it
    answers: ``(process, url)``. Its output goes to ``output`` (a pipe, text, by default). The
    caller stops it.

    :raises RuntimeError: if it does not come up (it is killed, and its output is in the message)
    """
    port = free_port()
    process = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "app.cli",
            "serve",
            "--port",
            str(port),
            *([] if "--workers" in args else ["--workers", "1"]),
            *args,
        ],
        stdout=output,
        stderr=subprocess.STDOUT,
        text=True,
        env={**os.environ, **(env or {}), "VANTAGE_DATA_DIR": str(data_dir)},
    )
    url = f"http://127.0.0.1:{port}"
    try:
        wait_until_up(url, process)
    except RuntimeError as error:
        process.kill()
        said = process.communicate()[0] if output == subprocess.PIPE else ""
        raise RuntimeError(f"{error}:\n{said}") from None
    return process, url


class Client:
    """The service's HTTP API, one method a route; errors raise ``httpx.HTTPStatusError``
    whose response carries the server's ``detail``."""

    def __init__(self, url: str, token: str | None = None, timeout: float = 300.0) -> None:
        headers = {"authorization": f"Bearer {token}"} if token else {}
        self.http = httpx.Client(base_url=url, headers=headers, timeout=timeout)

    def __enter__(self) -> Client:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        self.http.close()

    def _json(self, method: str, path: str, **kwargs: Any) -> Any:
        return self.http.request(method, path, **kwargs).raise_for_status().json()

    def documents(self) -> list[dict]:
        return self._json("GET", "/documents")

    def create_document(self, name: str) -> dict:
        return self._json("POST", "/documents", json={"name": name})

    def describe(self, doc: str) -> dict:
        return self._json("GET", f"/documents/{doc}")

    def import_items(self, doc: str, body: bytes | IO[bytes]) -> dict:
        """Bulk import NDJSON (bytes, or a file streamed from disk); ``{"imported", "version"}``."""
        return self._json("POST", f"/documents/{doc}/items", content=body, headers=NDJSON)

    def import_stream(self, doc: str, chunks: Iterable[bytes], replace: bool = False) -> dict:
        """Bulk import NDJSON sent as ``chunks`` come (chunked transfer: the body never sits
        in memory whole); ``replace``: the document's items become exactly these (the server's
        ``mode=replace``; see ``supports_replace``). If ``chunks`` raises, the upload is
        aborted and the server stores nothing."""
        params = {"mode": "replace"} if replace else None
        return self._json("POST", f"/documents/{doc}/items", content=chunks, headers=NDJSON, params=params)

    def supports_replace(self) -> bool:
        """Whether the server's import route takes ``mode=replace`` (from its OpenAPI schema:
        a server without it would ignore the parameter and upsert)."""
        schema = self._json("GET", "/openapi.json")
        route = schema.get("paths", {}).get("/documents/{doc}/items", {}).get("post", {})
        return any(
            p.get("name") == "mode" and p.get("in") == "query" and '"replace"' in json.dumps(p)
            for p in route.get("parameters", [])
        )

    def delete_document(self, doc: str) -> None:
        self.http.delete(f"/documents/{doc}").raise_for_status()

    def viewport(self, doc: str, rect: tuple[float, float, float, float], **params: Any) -> dict:
        """Items in ``rect``; ``params`` are the route's (``scale``, ``min_px``, ``limit``)."""
        return self._json(
            "GET",
            f"/documents/{doc}/viewport",
            params={**dict(zip(("x0", "y0", "x1", "y1"), rect, strict=True)), **params},
        )
