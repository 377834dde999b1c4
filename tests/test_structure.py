"""The app's shape: routers declare routes and call the modules that do the work; only the
app's assembly (``app/main.py``) imports a router; importing ``app.main`` starts nothing, and
the process's start-up runs before its app answers.

A router (``app/routers/*.py``) may define route functions (decorated ``@router.<verb>``),
private helpers of its routes (a leading ``_``: they read a request, word a response), request
bodies (pydantic models) and exceptions of its own that are not domain errors (those are
``app.errors``'). Anything else it defines (an answer function, a pool, a body reader) is work
another module must do, where the fast path (``app.hot``) and the other routes can call it.
"""

import ast
from pathlib import Path

from service import in_fresh_interpreter

import app.answers
from app.config import Settings
from app.main import create_app

APP = Path(app.answers.__file__).parent
ROUTERS = APP / "routers"


def _module_of(path: Path) -> str:
    parts = path.relative_to(APP.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _imported(path: Path) -> set[str]:
    """The modules ``path`` imports anywhere in it, relative imports resolved; for ``from X
    import y``, both ``X`` and ``X.y`` (``y`` may be a module)."""
    package = _module_of(path).split(".")
    if path.name != "__init__.py":
        package = package[:-1]
    found = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            found |= {alias.name for alias in node.names}
        elif isinstance(node, ast.ImportFrom):
            base = package[: len(package) - node.level + 1] if node.level else []
            module = ".".join([*base, *([node.module] if node.module else [])])
            found |= {module, *(f"{module}.{alias.name}" for alias in node.names)}
    return found


def _routes_module(name: str) -> bool:
    return name == "app.routers" or name.startswith("app.routers.")


def test_only_the_apps_assembly_imports_a_router():
    importers = {
        str(path.relative_to(APP.parent)): sorted(filter(_routes_module, _imported(path)))
        for path in sorted(APP.rglob("*.py"))
        if path != APP / "main.py"
    }
    assert {path: names for path, names in importers.items() if names} == {}


def _is_route(node: ast.FunctionDef | ast.AsyncFunctionDef) -> bool:
    """Decorated ``@router.get(...)`` (or any other of the router's verbs)."""
    for decorator in node.decorator_list:
        call = decorator.func if isinstance(decorator, ast.Call) else decorator
        if isinstance(call, ast.Attribute) and isinstance(call.value, ast.Name) and call.value.id == "router":
            return True
    return False


def _allowed_class(node: ast.ClassDef) -> bool:
    """A request body, or an exception of the router's own (not a domain error)."""
    return any(isinstance(base, ast.Name) and base.id in ("BaseModel", "Exception") for base in node.bases)


def _not_routing(path: Path) -> list[str]:
    """What the router ``path`` defines that is not a route, a private helper, a body or an
    exception of its own."""
    wrong = []
    for node in ast.parse(path.read_text(), str(path)).body:
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            if not _is_route(node) and not node.name.startswith("_"):
                wrong.append(f"{path.name}: {node.name}() is not a route: move it where it can be called")
        elif isinstance(node, ast.ClassDef) and not _allowed_class(node):
            wrong.append(f"{path.name}: class {node.name} is not a request body or the router's exception")
    return wrong


def test_a_router_defines_routes_and_their_private_helpers_only():
    routers = sorted(p for p in ROUTERS.glob("*.py") if p.name != "__init__.py")
    assert len(routers) >= 9  # every router is looked at
    assert [wrong for path in routers for wrong in _not_routing(path)] == []


def test_the_rule_sees_an_answer_function_moved_back_into_a_router(tmp_path):
    """The check itself: a copy of the viewport router given back a public answer function,
    and a pool class, is refused."""
    router = (ROUTERS / "viewport.py").read_text()
    moved_back = tmp_path / "viewport.py"
    moved_back.write_text(
        router + "\n\ndef viewport_answer(doc, settings):\n    return b''\n\n\nclass Searches:\n    pass\n"
    )
    assert _not_routing(moved_back) == [
        "viewport.py: viewport_answer() is not a route: move it where it can be called",
        "viewport.py: class Searches is not a request body or the router's exception",
    ]


def test_the_fast_path_answers_with_functions_outside_the_routers(tmp_path):
    """What ``app.hot`` calls for a viewport, a diff and a tile is what ``app.answers``
    builds, as the routes do: not a router's own (private) function."""
    hot = create_app(Settings(data_dir=tmp_path)).middleware_stack
    answers = {name: route.answer for name, route in hot.routes.items()} | {"tiles": hot.tile_answered}
    assert {name: fn.__module__ for name, fn in answers.items()} == dict.fromkeys(
        ("viewport", "diff", "tiles"), "app.answers"
    )


START_UP = r"""
import json, sys
import app.heap, app.housekeeping

called = []
app.heap.map_large_blocks = lambda: called.append("map_large_blocks")
app.housekeeping.warm_up = lambda *args: called.append("warm_up")
app.housekeeping.freeze_start_up_objects = lambda: called.append("freeze_start_up_objects")

import app.main

seen = {"imported": list(called), "app made": "app" in vars(app.main)}
if sys.argv[1] == "load":  # as uvicorn (and the workers' supervisor, before it forks) loads it
    app.main.app
    seen["loaded"] = list(called)
    seen["kept"] = app.main.app is app.main.app
else:  # an app made by create_app, as the tests make them: its lifespan starts up
    from fastapi.testclient import TestClient
    from app.config import Settings

    settings = Settings(data_dir=sys.argv[2], allowed_hosts="testserver")
    with TestClient(app.main.create_app(settings)) as client:
        seen["started"] = list(called)
        client.get("/health")
print(json.dumps(seen))
"""
STARTED = ["map_large_blocks", "warm_up", "freeze_start_up_objects"]  # in this order: frozen once warm


def test_importing_the_app_starts_nothing_and_loading_it_starts_the_process(tmp_path):
    # The child's app reads its settings from the environment: its data directory is here.
    script = f"import os; os.environ['VANTAGE_DATA_DIR'] = {str(tmp_path)!r}\n" + START_UP
    seen = in_fresh_interpreter(script, "load", timeout=120)
    assert seen == {"imported": [], "app made": False, "loaded": STARTED, "kept": True}


def test_an_apps_lifespan_starts_the_process_before_it_answers(tmp_path):
    seen = in_fresh_interpreter(START_UP, "lifespan", str(tmp_path), timeout=120)
    assert seen == {"imported": [], "app made": False, "started": STARTED}
