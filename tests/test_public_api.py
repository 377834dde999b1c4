"""Each module's public names are declared, sorted, and importable."""

import importlib

import pytest

MODULES = [
    "spatial",
    "spatial.quadtree",
    "spatial.rect",
    "spatial.overview",
    "spatial.raster",
    "spatial.scenes",
    "spatial._kernels",
    "app.access",
    "app.client",
    "app.answers",
    "app.blocks",
    "app.config",
    "app.looks",
    "app.deps",
    "app.documents",
    "app.errors",
    "app.examples",
    "app.guard",
    "app.heap",
    "app.hot",
    "app.housekeeping",
    "app.items",
    "app.launch",
    "app.main",
    "app.masks",
    "app.protocol",
    "app.registry",
    "app.responses",
    "app.session",
    "app.snapfile",
    "app.snapshots",
    "app.stores",
    "app.stores.base",
    "app.stores.postgres",
    "app.stores.sqlite",
    "app.table",
    "app.uploads",
]


@pytest.mark.parametrize("name", MODULES)
def test_all_is_sorted_and_resolves(name):
    module = importlib.import_module(name)
    assert module.__all__ == sorted(module.__all__)
    for public in module.__all__:
        assert hasattr(module, public), f"{name}.__all__ names missing {public}"
