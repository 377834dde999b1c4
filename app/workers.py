"""Serving on N worker processes, each accepting from a listening socket of its own.

When every worker accepts from one shared socket, which one gets a connection is left to the
kernel's wake-ups: a burst of connections (a load balancer's pool, a page's streams, a
reconnect after a restart) can all land on one worker, and keep-alive and WebSockets keep them
there. With ``SO_REUSEPORT`` (Linux) each worker listens on a socket of its own bound to the
same port, and the kernel hashes each new connection to one of them: an even spread, whatever
the arrival pattern (nginx's ``reuseport``, gunicorn's ``reuse_port``).

The supervisor loads the app (making ``app.main:app`` compiles the kernels) before it forks, so the
workers share the interpreter, numba's compiled code and start-up's objects, copy-on-write.
It holds every socket, so a worker that dies is replaced on its own socket and the connections
hashed there meanwhile wait in its queue instead of being refused.
"""

import contextlib
import logging
import os
import signal
import socket
import sys
import time

import uvicorn
from uvicorn.config import STARTUP_FAILURE
from uvicorn.supervisors import Multiprocess

__all__ = ["reuse_port_available", "serve"]

log = logging.getLogger("vantage")

#: How long a stopping worker has to finish its requests and streams before it is killed.
STOP_SECONDS = 30.0


def reuse_port_available() -> bool:
    """Whether the kernel balances connections across sockets sharing a port: Linux's
    ``SO_REUSEPORT`` does; the BSDs' and macOS's lets sockets share a port without balancing."""
    return sys.platform.startswith("linux") and hasattr(socket, "SO_REUSEPORT")


def serve(config: uvicorn.Config, workers: int) -> None:
    """Run ``config``'s app on ``workers`` processes until SIGINT or SIGTERM; one worker is
    this process itself. Exits with uvicorn's start-up failure code when a worker cannot
    start (its error is in the log), rather than restarting it for ever."""
    if workers == 1:
        uvicorn.Server(config).run()
        return
    if not hasattr(os, "fork"):
        log.warning("no fork() here: %d workers share one socket (uvicorn's own processes)", workers)
        config.workers = workers
        Multiprocess(config, sockets=[config.bind_socket()]).run()  # uvicorn >= 0.51: it makes the servers
        return
    config.load()  # before forking: the workers share the imported app and its compiled code
    sockets = _listening_sockets(config.host, config.port, workers)
    _Supervisor(config, sockets).run()


def _listening_sockets(host: str, port: int, count: int) -> list[socket.socket]:
    """``count`` sockets bound to ``host:port``: one each with ``SO_REUSEPORT``, or one shared
    by all where the kernel would not balance them.

    :raises SystemExit: with uvicorn's start-up failure code if the port is taken
    """
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    balanced = reuse_port_available()
    if not balanced:
        log.warning(
            "SO_REUSEPORT does not balance connections on %s: the %d workers share one socket, so "
            "which takes a connection is left to the kernel (put a load balancer in front to spread "
            "long-lived streams)",
            sys.platform,
            count,
        )
    sockets: list[socket.socket] = []
    try:
        if balanced:
            # A plain bind first: a port held by anyone, even another server with SO_REUSEPORT
            # (which would otherwise share our port and take half the connections), is refused.
            with socket.socket(family) as probe:
                probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
                probe.bind((host, port))
                port = probe.getsockname()[1]  # port 0: the one the kernel chose, for every socket
        for _ in range(count if balanced else 1):
            sock = socket.socket(family)
            sockets.append(sock)
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            if balanced:
                sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEPORT, 1)
            sock.bind((host, port))
            sock.set_inheritable(True)
    except OSError as error:
        for sock in sockets:
            sock.close()
        log.error("cannot listen on %s:%d: %s", host, port, error)
        sys.exit(STARTUP_FAILURE)
    log.info(
        "Uvicorn running on http://%s:%d with %d workers (%s)",
        host,
        port,
        count,
        "a socket each, SO_REUSEPORT" if balanced else "one shared socket",
    )
    return sockets * (count if len(sockets) == 1 else 1)


class _Supervisor:
    """Forks a worker per socket, replaces one that dies, and stops them all on a signal."""

    def __init__(self, config: uvicorn.Config, sockets: list[socket.socket]) -> None:
        self.config, self.sockets = config, sockets
        self.pids: dict[int, int] = {}  # worker pid -> its socket's index
        self.stopping = False

    def run(self) -> None:
        for signum in (signal.SIGINT, signal.SIGTERM):
            signal.signal(signum, self._stop)
        for slot in range(len(self.sockets)):
            self._fork(slot)
        failed = False
        while self.pids:
            try:
                pid, status = os.wait()
            except ChildProcessError:
                break
            index = self.pids.pop(pid, None)
            if index is None:
                continue
            code = os.waitstatus_to_exitcode(status)
            if self.stopping:
                continue
            if code == STARTUP_FAILURE:  # it would fail again: stop, and say so once
                log.error("worker %d could not start (exit code %d): stopping", pid, code)
                failed = True
                self._stop(signal.SIGTERM, None)
                continue
            log.warning("worker %d exited (%s): starting another on its socket", pid, _said(code))
            time.sleep(0.1)  # a worker that dies at once does not make a busy loop of this
            self._fork(index)
        for sock in self.sockets:
            sock.close()
        if failed:
            sys.exit(STARTUP_FAILURE)

    def _fork(self, index: int) -> None:
        pid = os.fork()
        if pid:
            self.pids[pid] = index
            return
        code = 0  # the child: serve on its own socket, never return into the supervisor
        try:
            for signum in (signal.SIGINT, signal.SIGTERM):
                signal.signal(signum, signal.SIG_DFL)  # uvicorn installs its own
            mine = self.sockets[index]
            for other in {id(s): s for s in self.sockets if s is not mine}.values():
                other.close()
            server = uvicorn.Server(self.config)
            server.run(sockets=[mine])
            code = STARTUP_FAILURE if not server.started else 0
        except SystemExit as exit_:
            code = exit_.code if isinstance(exit_.code, int) else 1
        except BaseException:
            log.exception("worker %d failed", os.getpid())
            code = 1
        finally:
            logging.shutdown()
            os._exit(code)

    def _stop(self, signum: int, frame: object) -> None:
        """Ask every worker to finish (what it is answering ends, then it exits); kill those
        still running after STOP_SECONDS."""
        if self.stopping:
            return
        self.stopping = True
        for pid in self.pids:
            _signal(pid, signal.SIGTERM)
        signal.signal(signal.SIGALRM, self._kill)
        signal.alarm(int(STOP_SECONDS))

    def _kill(self, signum: int, frame: object) -> None:
        for pid in self.pids:
            log.warning("worker %d did not stop within %.0f s: killed", pid, STOP_SECONDS)
            _signal(pid, signal.SIGKILL)


def _signal(pid: int, signum: int) -> None:
    with contextlib.suppress(ProcessLookupError):  # already gone; os.wait() reaps it
        os.kill(pid, signum)


def _said(code: int) -> str:
    return f"killed by {signal.Signals(-code).name}" if code < 0 else f"exit code {code}"
