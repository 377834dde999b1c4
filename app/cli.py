"""``vantage``: the command line."""

import argparse

from .config import get_settings

__all__ = ["main"]


def main(argv: list[str] | None = None) -> None:
    settings = get_settings()
    parser = argparse.ArgumentParser(prog="vantage", description=__doc__.strip("`: "))
    commands = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    serve = commands.add_parser("serve", help="run the HTTP/WebSocket service with uvicorn")
    serve.add_argument("--host", default=settings.host, help="address to bind (default %(default)s)")
    serve.add_argument("--port", type=int, default=settings.port, help="port (default %(default)s)")
    demo = commands.add_parser("demo", help="create the demo documents (a 2000-page report, a whiteboard)")
    demo.add_argument("--data-dir", default=str(settings.data_dir), help="store location (default %(default)s)")
    args = parser.parse_args(argv)

    if args.command == "serve":
        import uvicorn

        print(f"Vantage on http://{args.host}:{args.port}/  (API docs at /docs)", flush=True)
        uvicorn.run("app.main:app", host=args.host, port=args.port, log_level="warning")
    elif args.command == "demo":
        from pathlib import Path

        from .demo import create_demos
        from .store import Store

        store = Store(Path(args.data_dir))
        created = create_demos(store)
        store.close()
        print(f"created {', '.join(created)}" if created else "demo documents already present", flush=True)


if __name__ == "__main__":
    main()
