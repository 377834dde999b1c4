"""vantage: the command line of the Vantage service (serve, demo, import, check, simulate)."""

import argparse
import errno
import importlib.util
import os
import socket
import sys
from pathlib import Path

from .config import Settings, get_settings, is_loopback

__all__ = ["main"]


def main(argv: list[str] | None = None) -> None:
    settings = get_settings()
    parser = argparse.ArgumentParser(prog="vantage", description=__doc__.removeprefix("vantage: "))
    commands = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    serve = commands.add_parser("serve", help="run the HTTP/WebSocket service with uvicorn")
    serve.add_argument("--host", default=settings.host, help="address to bind (default %(default)s)")
    serve.add_argument("--port", type=int, default=settings.port, help="port (default %(default)s)")
    serve.add_argument(
        "--workers",
        type=int,
        default=os.cpu_count() or 1,
        help="processes serving on the port, each accepting from a socket of its own (SO_REUSEPORT) "
        "and sharing the store and each document's mapped snapshot (default: the cores, %(default)s)",
    )
    serve.add_argument(
        "--log-level",
        default="warning",
        choices=("debug", "info", "warning", "error"),
        help="info logs every request and each stream's totals (default %(default)s)",
    )
    demo = commands.add_parser("demo", help="create the demo documents (a 2000-page report, a whiteboard)")
    demo.add_argument(
        "--data-dir", default=str(settings.data_dir), help="store location (default %(default)s)"
    )
    imports = commands.add_parser(
        "import",
        help="import files (NDJSON, CSV, PDF, Excalidraw, tldraw...) into a document",
        description="Import files into a document: NDJSON (.ndjson, .jsonl), a JSON array of items, "
        "CSV with a header (id,x0,y0,x1,y1[,kind,z,...]), PDF (pages, words, images, drawings), "
        "Excalidraw (.excalidraw) or tldraw (.tldr), each gzipped too (.pdf.gz), found by its "
        "content. Into the local store, or through a "
        "running server with --url. All or nothing: a bad record stores nothing and is named. A "
        "local import names the store it writes, on stderr; it creates a new store only where "
        "--data-dir or VANTAGE_DATA_DIR says, never in the default ./data of whatever directory "
        "it runs in (a server reads the store in its own VANTAGE_DATA_DIR).",
    )
    imports.add_argument("paths", nargs="+", metavar="PATH", type=Path, help="files to import")
    imports.add_argument(
        "--doc",
        metavar="NAME|ID",
        help="the document, by id or name (created with that name if there is none); default: "
        "each file's own, named by its stem",
    )
    imports.add_argument(
        "--url", help="import through the server at this URL instead of into the local store"
    )
    imports.add_argument(
        "--token",
        default=os.environ.get("VANTAGE_TOKEN"),
        help="the server's bearer token (default $VANTAGE_TOKEN)",
    )
    imports.add_argument(
        "--replace",
        action="store_true",
        help="the document's items become exactly the file's (default: upsert by id)",
    )
    imports.add_argument(
        "--columns", type=int, default=1, metavar="N", help="PDF pages in N columns (default: stacked in one)"
    )
    imports.add_argument(
        "--data-dir",
        type=Path,
        help=f"the local store (default VANTAGE_DATA_DIR, {settings.data_dir}); created if it does "
        "not exist yet, which the default is not",
    )
    check = commands.add_parser(
        "check",
        help="check every document's snapshot file, every block of it, against its checksums",
        description="Check every document's snapshot file, every block of it, against its checksums "
        "(a server checks a block when it first reads it, so a block no request reads is checked "
        "only here). A corrupt file is removed: the next open builds it again from the store. "
        "Exits 1 if one was corrupt.",
    )
    check.add_argument(
        "--data-dir",
        type=Path,
        default=settings.data_dir,
        help="the local store (default VANTAGE_DATA_DIR, %(default)s)",
    )
    token = commands.add_parser(
        "token",
        help="mint a signed access token (VANTAGE_JWT_SECRET) for scripts and development",
        description="Mint a signed access token (JWT, HS256, with the first secret of "
        "VANTAGE_JWT_SECRET) granting documents to read or write. An app's backend mints these "
        "for its users the same way; see docs/operating.md, 'Access for many users'.",
    )
    token.add_argument(
        "--doc",
        dest="docs",
        action="append",
        default=[],
        metavar="ID[:read|write]",
        help="a document id (or * for every one) and its right, read by default; repeat for more",
    )
    token.add_argument("--create", action="store_true", help="the token may create documents")
    token.add_argument(
        "--ttl", default="1h", help="how long it is valid: 90s, 30m, 1h, 7d (default %(default)s)"
    )
    token.add_argument("--sub", help="who it is for: the server logs it beside each write")
    commands.add_parser(
        "simulate", help="load-test a server the way people pan (vantage simulate --help)", add_help=False
    )
    args, rest = parser.parse_known_args(argv)

    if args.command == "simulate":
        missing = [name for name in ("httpx", "matplotlib") if not _installed(name)]
        if missing:
            parser.exit(
                2, f"vantage simulate needs {' and '.join(missing)}: pip install 'vantage-canvas[simulate]'\n"
            )
        from .simulate import main as simulate

        simulate(rest)
        return
    if rest:
        parser.error(f"unrecognized arguments: {' '.join(rest)}")
    if args.command == "serve":
        import uvicorn

        if args.workers < 1:
            parser.error(f"--workers must be at least 1, got {args.workers}")
        open_writes = not settings.tokens_required
        host = args.host if not open_writes or is_loopback(args.host) else "127.0.0.1"
        taken = _port_taken(host, args.port)
        if taken:  # before anything slow, and before a URL is announced for a server that will not run
            parser.exit(1, f"vantage serve: {taken}\n")
        if open_writes:
            if host != args.host:
                print(
                    f"no VANTAGE_TOKENS set, so writes are open: serving on 127.0.0.1, not {args.host}",
                    flush=True,
                )
            print("writes are open to this machine only (set VANTAGE_TOKENS to require a token)", flush=True)
        # Each worker process imports app.main and reads its settings from the environment.
        os.environ.update(VANTAGE_HOST=host, VANTAGE_WORKERS=str(args.workers))
        get_settings.cache_clear()
        settings = get_settings()
        from .access import Access, BadKey
        from .stores import StoreError, open_store, where

        try:  # say now, in one line, why the store or the keys cannot be used (not in each worker's traceback)
            Access(settings)
            open_store(settings.data_dir, settings.database_url).close()
        except (StoreError, BadKey) as error:
            parser.exit(1, f"vantage serve: {error}\n")
        except OSError as error:  # the data directory: a file, not writable, on a full disk...
            parser.exit(1, f"vantage serve: the data directory {settings.data_dir} cannot be used: {error}\n")
        budget = settings.cache_bytes >> 20
        print(f"documents in {where(settings.data_dir, settings.database_url)}", flush=True)
        print(
            f"Vantage on http://{host}:{args.port}/  (API docs at /docs); {args.workers} worker"
            f"{'s' if args.workers > 1 else ''}, each keeping up to {budget} MB of documents open "
            "(VANTAGE_CACHE_MB)",
            flush=True,
        )
        from . import workers
        from .protocol import UVICORN_HTTP, UVICORN_WS

        config = uvicorn.Config(
            "app.main:app",
            http=UVICORN_HTTP,  # a response's head and body in one socket write
            ws=UVICORN_WS,  # a stream's send waits for its client to take the answer
            host=host,
            port=args.port,
            log_level=args.log_level,
            access_log=args.log_level in ("info", "debug"),  # a line a request, built only when shown
            log_config=_log_config(args.log_level.upper()),  # applied in every worker process
        )
        workers.serve(config, args.workers)
    elif args.command == "demo":
        from .demo import create_demos
        from .housekeeping import compiles_said
        from .stores import open_store

        store = open_store(Path(args.data_dir), settings.database_url)
        with compiles_said("vantage demo", _said):
            created = create_demos(store, Path(args.data_dir) / "snapshots")
        store.close()
        print(f"created {', '.join(created)}" if created else "demo documents already present", flush=True)
    elif args.command == "import":
        if argv is None and args.url is None and _bytes_of(args.paths) >= HUGE_PAGES_FROM:
            from .heap import with_huge_pages  # this program, importing here, a large import

            with_huge_pages()
        _import(parser, args)
    elif args.command == "check":
        _check(parser, args, settings)
    elif args.command == "token":
        print(_token(parser, args, settings), flush=True)


# An import's bytes from which it starts again in huge pages (app.heap). Measured on NDJSON
# boards, taking turns: 1.10x the time at 125 MiB, even at 375 MiB, 0.94x at 626 MiB, 0.85x at
# 1.2 GiB (starting again, ~0.3 s, and huge pages' zeroing outweigh the faults saved below).
HUGE_PAGES_FROM = 512 << 20


def _said(line: str) -> None:
    print(line, file=sys.stderr, flush=True)


def _bytes_of(paths: list[Path]) -> int:
    """The bytes of the files among ``paths``: a small import does not start again for huge
    pages (see ``HUGE_PAGES_FROM``)."""
    return sum(path.stat().st_size for path in paths if path.is_file())


def _import(parser: argparse.ArgumentParser, args: argparse.Namespace) -> None:
    from .importers.base import ImportFailed
    from .importers.command import import_local, import_remote, plan

    if args.columns < 1:
        parser.error(f"--columns must be at least 1, got {args.columns}")
    try:
        groups = plan(args.paths, args.doc, args.columns)
        if args.url is not None:
            said = import_remote(groups, args.url.rstrip("/"), args.token, args.replace)
        else:
            from .housekeeping import compiles_said

            store = _local_store(parser, args)
            with compiles_said("vantage import", _said):
                said = import_local(groups, store, args.replace)
    except ImportFailed as error:
        parser.exit(1, f"vantage import: {error}\n")
    except KeyboardInterrupt:
        parser.exit(130, "vantage import: interrupted; nothing of the import under way was stored\n")
    for line in said:
        print(line, flush=True)


def _local_store(parser: argparse.ArgumentParser, args: argparse.Namespace) -> Path:
    """The data directory a local import writes, named on stderr. A store that does not exist
    yet is created only where the user said (``--data-dir`` or VANTAGE_DATA_DIR): the default,
    ./data, is relative to wherever the command runs, where no server may read it."""
    from .stores import where

    settings = get_settings()
    explicit = args.data_dir is not None or "data_dir" in settings.model_fields_set
    data_dir = (args.data_dir or settings.data_dir).absolute()
    store = where(data_dir, settings.database_url)
    if settings.database_url or (data_dir / "vantage.sqlite3").exists():
        print(f"vantage import: into {store}", file=sys.stderr, flush=True)
    elif explicit:
        print(
            f"vantage import: into {store}, a new store: it does not exist yet and is created "
            f"(a server reads it with VANTAGE_DATA_DIR={data_dir})",
            file=sys.stderr,
            flush=True,
        )
    else:
        parser.exit(
            2,
            f"vantage import: no store at {data_dir} (the default, ./data, of the directory this runs in): "
            "to create one, say where with --data-dir DIR or VANTAGE_DATA_DIR (the directory a server "
            "reads), or import through a running server with --url\n",
        )
    return data_dir


def _token(parser: argparse.ArgumentParser, args: argparse.Namespace, settings: Settings) -> str:
    from .access import BadKey, hmac_secrets, mint

    try:  # the server's own rule: a token it would refuse to verify is never signed
        secrets = hmac_secrets(settings.jwt_secret)
    except BadKey as error:
        parser.exit(2, f"vantage token: {error}\n")
    if not secrets:
        parser.exit(2, "vantage token: set VANTAGE_JWT_SECRET (the server's secret) to mint tokens\n")
    if not args.docs and not args.create:
        parser.error(
            "name a document (--doc ID[:read|write]) or --create: a token granting nothing is no use"
        )
    docs = {}
    for given in args.docs:
        doc, _, right = given.rpartition(":") if given.endswith((":read", ":write")) else (given, "", "read")
        docs[doc] = right
    units = {"s": 1, "m": 60, "h": 3600, "d": 86400}
    ttl = args.ttl.strip().lower()
    try:
        seconds = float(ttl[:-1]) * units[ttl[-1]] if ttl[-1:] in units else float(ttl)
    except ValueError:
        parser.error(f"--ttl {args.ttl!r}: a duration such as 90s, 30m, 1h or 7d")
    if seconds <= 0:
        parser.error(f"--ttl {args.ttl!r}: it must be positive")
    return mint(
        secrets[0].decode(),
        docs,
        seconds,
        create=args.create,
        subject=args.sub,
        audience=settings.jwt_audience or None,
    )


def _check(parser: argparse.ArgumentParser, args: argparse.Namespace, settings: Settings) -> None:
    from .snapfile import SnapshotFiles
    from .stores import StoreError, open_store

    try:
        store = open_store(args.data_dir, settings.database_url)
    except StoreError as error:
        parser.exit(1, f"vantage check: {error}\n")
    try:
        said = SnapshotFiles(args.data_dir / "snapshots").check(store)
    finally:
        store.close()
    for line in said:
        print(line, flush=True)
    if any(" corrupt" in line for line in said):
        parser.exit(1)


def _port_taken(host: str, port: int) -> str | None:
    """Why ``host:port`` cannot be listened on (in use, not this machine's address), or None.
    A plain bind, as the server's own: a port another server holds, even with SO_REUSEPORT, is
    taken."""
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    with socket.socket(family) as probe:
        probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            probe.bind((host, port))
        except OSError as error:
            if error.errno == errno.EADDRINUSE:
                return f"port {port} on {host} is in use: stop what holds it, or serve on another with --port"
            return f"cannot listen on {host}:{port}: {error.strerror}"
    return None


def _log_config(level: str) -> dict:
    """Every logger (uvicorn's and the service's) to stderr, one plain line a record."""
    return {
        "version": 1,
        "disable_existing_loggers": False,
        "formatters": {"plain": {"format": "%(levelname)s: %(name)s: %(message)s"}},
        "handlers": {"err": {"class": "logging.StreamHandler", "formatter": "plain"}},
        "root": {"handlers": ["err"], "level": level},
        "loggers": {name: {"level": level} for name in ("uvicorn", "uvicorn.error", "uvicorn.access")},
    }


def _installed(name: str) -> bool:
    try:
        return importlib.util.find_spec(name) is not None
    except ValueError:  # in sys.modules as None: hidden on purpose
        return False


if __name__ == "__main__":
    main()
