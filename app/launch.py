"""Starting and stopping Vantage servers as processes, for the simulator, the benchmarks and the
tests: ``launch`` runs ``vantage serve`` on a free loopback port and returns once it answers::

    process, url = launch(Path("data"), "--log-level", "info")
    try:
        ...  # talk to url, with app.client.Client say
    finally:
        stop(process)
"""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path
from typing import IO, Any

import httpx

__all__ = ["free_port", "launch", "stop", "wait_until_up"]


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


def stop(process: subprocess.Popen, timeout: float = 10.0, sig: int = signal.SIGTERM) -> bool:
    """Stop ``process``: ``sig``, then SIGKILL if it is still running after ``timeout`` seconds.
    Whether it stopped by itself."""
    process.send_signal(sig)
    try:
        process.wait(timeout=timeout)
    except subprocess.TimeoutExpired:
        process.kill()
        process.wait()
        return False
    return True


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
