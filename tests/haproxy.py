"""Debian's HAProxy in front of replicas, with the repository's deploy/haproxy.cfg.

    from haproxy import haproxy_front

    with haproxy_front(["127.0.0.1:8001", "127.0.0.1:8002"]) as url:
        httpx.get(f"{url}/documents")  # url: http://127.0.0.1:<port>

The binary is /usr/sbin/haproxy (``./test`` installs the ``haproxy`` package on a fresh
machine), or the one ``VANTAGE_HAPROXY`` names. HAProxy stops by itself if the thread that
started it ends first (a parent-death signal, so that a test run killed midway leaves none
behind): start it from the main thread, as fixtures are.
"""

import os
import subprocess
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from app.launch import free_port, stop, wait_until_up

__all__ = ["CONFIG", "HaproxyMissing", "haproxy_front", "haproxy_path"]

CONFIG = Path(__file__).resolve().parents[1] / "deploy" / "haproxy.cfg"
DEFAULT_HAPROXY = "/usr/sbin/haproxy"
START_TIMEOUT = 20.0


class HaproxyMissing(RuntimeError):
    """No HAProxy binary where the tests look for one."""


def haproxy_path() -> str:
    """The HAProxy to run: ``$VANTAGE_HAPROXY``, else Debian's ``/usr/sbin/haproxy``."""
    path = os.environ.get("VANTAGE_HAPROXY") or DEFAULT_HAPROXY
    if not os.access(path, os.X_OK):
        raise HaproxyMissing(
            f"no HAProxy at {path}: the tests need Debian's haproxy package "
            "(apt-get install haproxy), or VANTAGE_HAPROXY set to a haproxy binary"
        )
    return path


@contextmanager
def haproxy_front(replicas: list[str]) -> Iterator[str]:
    """HAProxy on a free loopback port balancing ``replicas`` (``host:port`` each, two at
    least), in the foreground; yields its base URL, ``http://127.0.0.1:<port>``, once
    ``GET /health`` answers 200 through it, and stops it on exit.

    The configuration is deploy/haproxy.cfg as it is; for a third replica and more, a copy with
    one ``server`` line added for each, as its comments say to do.

    :raises HaproxyMissing: if there is no haproxy binary
    :raises RuntimeError: if it does not answer within 20 s (with what it printed)
    """
    if len(replicas) < 2:
        raise ValueError(f"deploy/haproxy.cfg names two replicas at least, not {len(replicas)}")
    haproxy = haproxy_path()
    port = free_port()
    env = {**os.environ, "VANTAGE_FRONT": f"127.0.0.1:{port}"}
    env.update({f"VANTAGE_REPLICA{n}": address for n, address in enumerate(replicas, 1)})
    with tempfile.TemporaryDirectory(prefix="vantage-haproxy-") as scratch:
        config = CONFIG
        if len(replicas) > 2:
            config = Path(scratch) / "haproxy.cfg"
            config.write_text(_with_more_replicas(CONFIG.read_text(), len(replicas)))
        log_path = Path(scratch) / "haproxy.log"
        with log_path.open("wb") as log:
            process = subprocess.Popen(
                # -db: the foreground, one process; setpriv: it stops if the thread starting it ends
                ["setpriv", "--pdeathsig", "TERM", "--", haproxy, "-db", "-f", config],
                stdin=subprocess.DEVNULL,
                stdout=log,
                stderr=subprocess.STDOUT,
                env=env,
            )
        url = f"http://127.0.0.1:{port}"
        try:
            _wait_until_up(url, process, log_path)
            yield url
        finally:
            stop(process)


def _wait_until_up(url: str, process: subprocess.Popen, log_path: Path) -> None:
    try:
        wait_until_up(url, process, START_TIMEOUT)
    except RuntimeError as error:
        raise RuntimeError(f"haproxy: {error}; it printed:\n{log_path.read_text(errors='replace')}") from None


def _with_more_replicas(config: str, count: int) -> str:
    """``config`` with a ``server`` line for replicas 3 to ``count`` after replica2's."""
    anchor = 'server replica2 "${VANTAGE_REPLICA2}" check\n'
    if anchor not in config:
        raise RuntimeError(f"{CONFIG} has no line {anchor.strip()!r} to add replicas after")
    added = "".join(f'    server replica{n} "${{VANTAGE_REPLICA{n}}}" check\n' for n in range(3, count + 1))
    return config.replace(anchor, anchor + added)
