"""Every module of ``app`` and ``spatial``, found by walking the packages (a new module cannot be
missed): its public names are declared in ``__all__``, sorted, and importable; ``spatial``'s
public modules say what they promise; and ``app`` uses only ``spatial``'s public API, no module
or name of it whose name starts with ``_``."""

import ast
import importlib
import importlib.util
import inspect
import pkgutil
from pathlib import Path

import pytest

import app
import spatial

PACKAGES = (app, spatial)


def _modules() -> list[str]:
    names = []
    for package in PACKAGES:
        names.append(package.__name__)
        for found in pkgutil.walk_packages(package.__path__, f"{package.__name__}."):
            if found.name.rpartition(".")[2] != "__main__":  # a script: importing it runs it
                names.append(found.name)
    return sorted(names)


def _sources(package) -> list[Path]:
    root = Path(package.__file__).parent
    return sorted(p for p in root.rglob("*.py") if "__pycache__" not in p.parts and p.name != "__main__.py")


MODULES = _modules()
PUBLIC_SPATIAL = [name for name in MODULES if name.startswith("spatial") and "._" not in name]
APP_SOURCES = _sources(app)


def test_the_walk_finds_every_module_file_of_both_packages():
    # a folder without an __init__.py (or a package that fails to import) would hide its
    # modules from the walk: every file is one of them
    found = {Path(importlib.util.find_spec(name).origin) for name in MODULES}
    files = {path for package in PACKAGES for path in _sources(package)}
    assert not files - found, f"modules the walk did not find: {sorted(map(str, files - found))}"
    assert {"spatial.paging", "spatial._kernels", "app.stores.sqlite", "app.routers.viewport"} <= set(MODULES)


@pytest.mark.parametrize("name", MODULES)
def test_all_is_declared_sorted_and_resolves(name):
    module = importlib.import_module(name)
    assert hasattr(module, "__all__"), f"{name} declares no __all__: list its public names"
    assert module.__all__ == sorted(module.__all__), f"{name}.__all__ is not sorted"
    for public in module.__all__:
        assert hasattr(module, public), f"{name}.__all__ names missing {public}"


@pytest.mark.parametrize("name", PUBLIC_SPATIAL)
def test_a_public_spatial_module_says_what_it_promises(name):
    module = importlib.import_module(name)
    assert inspect.getdoc(module), f"{name} has no module docstring"
    for public in module.__all__:
        value = getattr(module, public)
        if (inspect.isfunction(value) or inspect.isclass(value)) and value.__module__ == name:
            assert inspect.getdoc(value), f"{name}.{public} has no docstring"


def private_spatial_names(source: str) -> list[str]:
    """The names of ``spatial``'s own (a module or a name starting with ``_``) that ``source``
    imports or reaches through an imported module."""
    found, bound = [], set()  # bound: local names of spatial's modules
    tree = ast.parse(source)
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for alias in node.names:
                if alias.name.split(".")[0] == "spatial":
                    found += [alias.name] if _private(alias.name) else []
                    bound.add(alias.asname or "spatial")
        elif isinstance(node, ast.ImportFrom) and not node.level and node.module:
            if node.module.split(".")[0] != "spatial":
                continue
            if _private(node.module):
                found.append(node.module)
            for alias in node.names:
                if alias.name.startswith("_"):
                    found.append(f"{node.module}.{alias.name}")
                bound.add(alias.asname or alias.name)
    for node in ast.walk(tree):
        if (
            isinstance(node, ast.Attribute)
            and isinstance(node.value, ast.Name)
            and node.value.id in bound
            and node.attr.startswith("_")
            and not node.attr.startswith("__")
        ):
            found.append(f"{node.value.id}.{node.attr}")
    return found


def _private(dotted: str) -> bool:
    return any(part.startswith("_") for part in dotted.split("."))


@pytest.mark.parametrize("path", APP_SOURCES, ids=lambda p: str(p.relative_to(Path(app.__file__).parent)))
def test_app_imports_no_private_spatial_name(path):
    private = private_spatial_names(path.read_text())
    assert not private, f"{path.name} uses spatial's own {private}: use (or make) a public name"


@pytest.mark.parametrize(
    "source",
    [
        "from spatial._paging import steps",
        "from spatial import _kernels",
        "import spatial._copy",
        "import spatial._copy as copying",
        "from spatial.paging import _copy",
        "from spatial import paging\npaging._kernels.bounds",
        "import spatial\nspatial._kernels",
        "def f():\n    from spatial._sorting import sorted_keys",
    ],
)
def test_the_check_finds_each_way_to_reach_a_private_spatial_name(source):
    assert private_spatial_names(source)


def test_the_check_passes_public_names_and_others_private_ones():
    source = (
        "import spatial\nimport spatial.paging as paging\nfrom spatial import QuadTree, sorting\n"
        "from spatial.kernels import copy\nfrom app import _x\nfrom ._y import z\n"
        "paging.steps, sorting.__doc__, spatial.budget, os._exit"
    )
    assert private_spatial_names(source) == []
