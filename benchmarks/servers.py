"""Spawning and stopping the uvicorn servers that service_bench measures.

Each server runs in a process group of its own, so stopping it (also on Ctrl-C or a failure,
through ``with``) takes down anything it started, and the load generators never share a group
with it.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from types import TracebackType

from app.launch import free_port, wait_until_up
from app.protocol import UVICORN_HTTP, UVICORN_WS

# The flags every server under test gets: one worker, no per-request logging.
UVICORN_FLAGS = ["--no-access-log", "--log-level", "warning"]
HOST = "127.0.0.1"
ROOT = Path(__file__).resolve().parent.parent  # apps are imported from the repository root


# The HTTP protocol ``vantage serve`` runs: a response's head and body in one socket write.
VANTAGE_HTTP = ["--http", UVICORN_HTTP, "--ws", UVICORN_WS]


def vantage_server(name: str, env: dict[str, str], log_dir: Path) -> Server:
    """A Vantage server run as ``vantage serve`` runs it (its HTTP protocol)."""
    return Server(name, "app.main:app", env, log_dir, VANTAGE_HTTP)


def rss_bytes(pid: int) -> int:
    """VmRSS of a process, from /proc/<pid>/status."""
    with open(f"/proc/{pid}/status") as f:
        for line in f:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) * 1024
    raise RuntimeError(f"no VmRSS for pid {pid}")


class Server:
    """``python -m uvicorn <app>`` on a free port, with its output in a log file."""

    def __init__(
        self,
        name: str,
        app: str,
        env: dict[str, str],
        log_dir: Path,
        flags: Sequence[str] = (),
        root: Path = ROOT,  # the tree whose app it runs (benchmarks.against runs another version's)
    ) -> None:
        self.name, self.app, self.port, self.flags, self.root = name, app, free_port(), list(flags), root
        self.env = {**os.environ, **env}
        self.log_path = log_dir / f"{name}.log"
        self.proc: subprocess.Popen | None = None
        self.started_at = 0.0

    @property
    def url(self) -> str:
        return f"http://{HOST}:{self.port}"

    @property
    def pid(self) -> int:
        assert self.proc is not None, f"{self.name} is not running"
        return self.proc.pid

    def start(self) -> Server:
        cmd = [
            sys.executable,
            "-m",
            "uvicorn",
            self.app,
            "--host",
            HOST,
            "--port",
            str(self.port),
            *UVICORN_FLAGS,
            *self.flags,
        ]
        with open(self.log_path, "ab") as log:
            self.started_at = time.perf_counter()
            self.proc = subprocess.Popen(
                cmd, env=self.env, stdout=log, stderr=subprocess.STDOUT, start_new_session=True, cwd=self.root
            )
        return self

    def wait_ready(self, path: str = "/health", timeout: float = 300.0) -> float:
        """Seconds from start() until ``path`` answers 200; fails with the log's tail if it dies."""
        try:
            wait_until_up(self.url, self.proc, timeout, path)
        except RuntimeError as error:
            raise RuntimeError(f"{self.name}: {error}:\n{self.log_tail()}") from None
        return time.perf_counter() - self.started_at

    def rss(self) -> int:
        return rss_bytes(self.pid)

    def stop(self, grace: float = 10.0) -> None:
        """SIGTERM the server's process group, SIGKILL it if it lingers."""
        if self.proc is None or self.proc.poll() is not None:
            self.proc = None
            return
        pgid = self.proc.pid  # start_new_session: the group id is the leader's pid
        try:
            os.killpg(pgid, signal.SIGTERM)
            self.proc.wait(grace)
        except subprocess.TimeoutExpired:
            os.killpg(pgid, signal.SIGKILL)
            self.proc.wait()
        except ProcessLookupError:
            pass
        self.proc = None

    def log_tail(self, lines: int = 30) -> str:
        try:
            return "\n".join(self.log_path.read_text(errors="replace").splitlines()[-lines:])
        except OSError:
            return "(no log)"

    def __enter__(self) -> Server:
        return self

    def __exit__(
        self, kind: type[BaseException] | None, error: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.stop()
