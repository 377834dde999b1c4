"""``vantage``: the command line."""

import argparse
import importlib.util
import logging

from .config import get_settings, is_loopback

__all__ = ["main"]


def main(argv: list[str] | None = None) -> None:
    settings = get_settings()
    parser = argparse.ArgumentParser(prog="vantage", description=__doc__.strip("`: "))
    commands = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    serve = commands.add_parser("serve", help="run the HTTP/WebSocket service with uvicorn")
    serve.add_argument("--host", default=settings.host, help="address to bind (default %(default)s)")
    serve.add_argument("--port", type=int, default=settings.port, help="port (default %(default)s)")
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

        from .main import create_app

        logging.basicConfig(level=args.log_level.upper(), format="%(levelname)s: %(name)s: %(message)s")
        host = args.host
        if not settings.tokens_required:
            if not is_loopback(host):
                print(
                    f"no VANTAGE_TOKENS set, so writes are open: serving on 127.0.0.1, not {host}", flush=True
                )
            host = host if is_loopback(host) else "127.0.0.1"
            print("writes are open to this machine only (set VANTAGE_TOKENS to require a token)", flush=True)
        print(f"Vantage on http://{host}:{args.port}/  (API docs at /docs)", flush=True)
        app = create_app(settings.model_copy(update={"host": host}))
        uvicorn.run(app, host=host, port=args.port, log_level=args.log_level)
    elif args.command == "demo":
        from pathlib import Path

        from .demo import create_demos
        from .store import Store

        store = Store(Path(args.data_dir))
        created = create_demos(store)
        store.close()
        print(f"created {', '.join(created)}" if created else "demo documents already present", flush=True)


def _installed(name: str) -> bool:
    try:
        return importlib.util.find_spec(name) is not None
    except ValueError:  # in sys.modules as None: hidden on purpose
        return False


if __name__ == "__main__":
    main()
