"""A real PostgreSQL server from Debian's packages, for tests of the service on PostgreSQL.

    from postgres import postgres_server

    with postgres_server(tmp_path / "postgres") as server:
        psycopg.connect(server.url)  # postgresql://vantage@127.0.0.1:<port>/vantage
        server.stop()                # and server.start() again: same port, same data

The binaries are the newest under /usr/lib/postgresql/<version>/bin (``./test`` installs the
``postgresql`` package on a fresh machine), or those in the directory ``VANTAGE_PG_BIN`` names.
PostgreSQL refuses to run as root: as root, the server runs as the system user ``vantage-pg``
(made on first use; ``nobody`` if it cannot be), with its data in a directory of its own under
the system's temporary directory, which that user can reach (pytest's are private to root).

The server stops by itself if the thread that started it ends first (a parent-death signal, so
that a test run killed midway leaves no server behind): start it from the main thread, as
fixtures are.
"""

import os
import pwd
import random
import shutil
import signal
import socket
import subprocess
import tempfile
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import psycopg

from app.launch import stop

__all__ = ["PostgresMissing", "PostgresServer", "pg_bin", "postgres_server"]

SERVER_USER = "vantage-pg"
DATABASE = "vantage"  # also the superuser's name
START_TIMEOUT = 30.0
STOP_TIMEOUT = 30.0

# Settings for a disposable server: nothing survives a machine crash, and tests do not need it
# to. A clean stop still writes everything (a fast shutdown ends with a checkpoint), so a
# restart finds every committed row.
SETTINGS = {
    "listen_addresses": "'127.0.0.1'",
    "max_connections": "200",
    "fsync": "off",
    "synchronous_commit": "off",
    "full_page_writes": "off",
}


class PostgresMissing(RuntimeError):
    """No PostgreSQL server binaries where the tests look for them."""


def pg_bin() -> Path:
    """The directory of the server binaries: ``$VANTAGE_PG_BIN``, else Debian's newest.

    :raises PostgresMissing: if neither holds ``initdb`` and ``postgres``
    """
    if named := os.environ.get("VANTAGE_PG_BIN"):
        candidates = [Path(named)]
    else:
        found = Path("/usr/lib/postgresql").glob("*/bin")
        candidates = sorted(found, key=lambda p: _version(p.parent.name), reverse=True)
    for directory in candidates:
        if all(os.access(directory / name, os.X_OK) for name in ("initdb", "postgres")):
            return directory
    raise PostgresMissing(
        f"no PostgreSQL server binaries in {named or '/usr/lib/postgresql/*/bin'}: the tests need "
        "Debian's postgresql package (apt-get install postgresql), or VANTAGE_PG_BIN set to the "
        "directory holding initdb and postgres"
    )


class PostgresServer:
    """One server on a private port and data directory, which can be stopped and started again.

    ``url`` names the ``vantage`` database as the trusted superuser ``vantage``; it is the same
    across restarts.
    """

    def __init__(self, directory: Path, *, bin_dir: Path | None = None) -> None:
        self.directory = Path(directory)
        self.bin = bin_dir or pg_bin()
        self._user = _server_user() if os.geteuid() == 0 else None
        self.home = self.directory if self._user is None else None  # as root: made by create()
        self.log_path = self.directory / "server.log"
        self.port = _free_port()
        self.url = self._url(DATABASE)
        self._process: subprocess.Popen | None = None

    @property
    def data(self) -> Path:
        """The data directory."""
        return self.home / "data"

    @property
    def sockets(self) -> Path:
        """The Unix-domain socket's directory, private to this server."""
        return self.home / "sockets"

    @property
    def pid(self) -> int | None:
        """The postmaster's process id while it runs."""
        return self._process.pid if self._process is not None else None

    def log(self) -> str:
        """What the server wrote so far (all its starts)."""
        return self.log_path.read_text(errors="replace") if self.log_path.exists() else ""

    def create(self) -> None:
        """initdb the data directory and make the ``vantage`` database; leaves the server running."""
        self.directory.mkdir(parents=True, exist_ok=True)
        if self._user is not None:
            self.home = Path(tempfile.mkdtemp(prefix="vantage-pg-"))
            self.home.chmod(0o711)  # the server's user passes through to its own directories
        for path in (self.data, self.sockets):
            path.mkdir(mode=0o700)
            if self._user is not None:
                os.chown(path, *self._user)
        initdb = self._run(
            [
                self.bin / "initdb",
                "--pgdata",
                self.data,
                "--username",
                DATABASE,
                "--auth=trust",
                "--encoding=UTF8",
                "--locale=C.UTF-8",
                "--no-sync",  # a test server's files need not reach the disk
            ],
        )
        if initdb.returncode != 0:
            raise RuntimeError(f"initdb failed ({initdb.returncode}):\n{initdb.stdout}")
        settings = {
            **SETTINGS,
            "port": str(self.port),
            # a private socket directory: another server on this machine may use the same port number
            "unix_socket_directories": f"'{self.sockets}'",
        }
        with (self.data / "postgresql.conf").open("a") as conf:
            conf.write("\n# tests/postgres.py\n")
            conf.writelines(f"{name} = {value}\n" for name, value in settings.items())
        self.start()
        self.new_database(DATABASE)

    def start(self) -> None:
        """Start the server on its port and data; returns once it accepts connections.

        :raises RuntimeError: if it is running already, or does not come up within 30 s (with
            its log)
        """
        if self._process is not None:
            raise RuntimeError("the PostgreSQL server is running already")
        with self.log_path.open("ab") as log:
            self._process = subprocess.Popen(
                # setpriv: the server stops if the thread starting it ends without stopping it
                ["setpriv", "--pdeathsig", "INT", "--", self.bin / "postgres", "-D", self.data],
                stdin=subprocess.DEVNULL,
                stdout=log,
                stderr=subprocess.STDOUT,
                cwd=self.home,  # one the server's user can reach
                env=_environment(),
                **self._as_user(),
            )
        deadline = time.monotonic() + START_TIMEOUT
        while True:
            try:
                psycopg.connect(self._url("postgres"), connect_timeout=2).close()
                return
            except psycopg.OperationalError as error:
                failure = error
            if self._process.poll() is not None:
                code, self._process = self._process.returncode, None
                raise RuntimeError(f"the PostgreSQL server exited ({code}) as it started:\n{self.log()}")
            if time.monotonic() > deadline:
                self.stop()
                raise RuntimeError(
                    f"the PostgreSQL server did not accept connections within {START_TIMEOUT:g} s "
                    f"({failure}):\n{self.log()}"
                )
            time.sleep(0.05)

    def stop(self) -> None:
        """Stop the server as ``pg_ctl stop -m fast`` does (SIGINT: end the sessions, checkpoint,
        exit); a server still up after 30 s is killed. Does nothing if it is not running."""
        process, self._process = self._process, None
        if process is None:
            return
        if not stop(process, STOP_TIMEOUT, signal.SIGINT):
            raise RuntimeError(
                f"the PostgreSQL server did not stop within {STOP_TIMEOUT:g} s; killed:\n{self.log()}"
            )

    def remove(self) -> None:
        """Stop the server and remove its files."""
        try:
            self.stop()
        finally:
            if self.home is not None and self.home != self.directory:
                shutil.rmtree(self.home, ignore_errors=True)
            shutil.rmtree(self.directory, ignore_errors=True)

    def new_database(self, name: str) -> str:
        """Create the database ``name`` (an SQL identifier) on the running server; its URL."""
        with psycopg.connect(self._url("postgres"), autocommit=True) as connection:
            connection.execute(f"CREATE DATABASE {name}")
        return self._url(name)

    def _url(self, database: str) -> str:
        return f"postgresql://{DATABASE}@127.0.0.1:{self.port}/{database}"

    def _as_user(self) -> dict:
        if self._user is None:
            return {}
        uid, gid = self._user
        return {"user": uid, "group": gid, "extra_groups": []}

    def _run(self, command: list) -> subprocess.CompletedProcess:
        return subprocess.run(
            command,
            stdin=subprocess.DEVNULL,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
            cwd=self.home,  # one the server's user can reach
            env=_environment(),
            **self._as_user(),
        )


@contextmanager
def postgres_server(directory: Path) -> Iterator[PostgresServer]:
    """A fresh server with its files in ``directory`` (made if missing; as root, its log alone),
    running; on exit it is stopped and its files removed.

    :raises PostgresMissing: if there are no server binaries
    :raises RuntimeError: if the server does not come up (with its log)
    """
    server = PostgresServer(directory)
    try:
        server.create()
        yield server
    finally:
        server.remove()


def _version(name: str) -> tuple[int, ...]:
    """ "15" -> (15,), "9.6" -> (9, 6); a name that is not a version sorts first."""
    try:
        return tuple(int(part) for part in name.split("."))
    except ValueError:
        return ()


def _free_port() -> int:
    """A free port below Linux's ephemeral range (32768 up): one the kernel gives out for
    outgoing connections could be taken while the server is stopped, and it restarts on it."""
    rng = random.Random()
    for _ in range(200):
        port = rng.randrange(20000, 32000)
        with socket.socket() as probe:
            try:
                probe.bind(("127.0.0.1", port))
            except OSError:
                continue
            return port
    raise RuntimeError("no free port between 20000 and 32000 for PostgreSQL")


def _environment() -> dict[str, str]:
    # libpq's PG* variables (PGDATA, PGPORT, ...) would override what the command line says
    return {name: value for name, value in os.environ.items() if not name.startswith("PG")}


def _server_user() -> tuple[int, int]:
    """The unprivileged ``(uid, gid)`` a root process runs the server as."""
    try:
        entry = pwd.getpwnam(SERVER_USER)
    except KeyError:
        subprocess.run(
            [
                "useradd",
                "--system",
                "--user-group",
                "--no-create-home",
                "--home-dir",
                "/nonexistent",
                "--shell",
                "/usr/sbin/nologin",
                "--comment",
                "PostgreSQL servers of the Vantage tests",
                SERVER_USER,
            ],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        )
        try:
            entry = pwd.getpwnam(SERVER_USER)  # made now, or by a concurrent run
        except KeyError:
            entry = pwd.getpwnam("nobody")
    return entry.pw_uid, entry.pw_gid
