"""The Python client as a user's type checker sees it: mypy, run over code that awaits every
public method of AsyncClient (and calls every one of Client), finds each typed as what it
returns; and the two clients take the same parameters, so neither drifts from the other."""

import inspect
import subprocess
import sys
import textwrap

import pytest
from service import ROOT

from app.client import AsyncClient, Client

# every public method of each, used as a user would, its result's type asserted exactly
# (assert_type: an Any, or a coroutine where a dict should be, is an error)
USER_CODE = """
from pathlib import Path
from typing import Any, assert_type

from app.client import AsyncClient, AsyncStream, Client, Stream, VantageError

BOX = (0.0, 0.0, 100.0, 100.0)
ITEM = {"id": "a", "x0": 0, "y0": 0, "x1": 1, "y1": 1}


async def asynchronously(url: str) -> None:
    async with AsyncClient(url, token=lambda: "fresh") as client:
        assert_type(client, AsyncClient)
        assert_type(await client.health(), dict[Any, Any])
        assert_type(await client.stats(), dict[Any, Any])
        assert_type(await client.supports_replace(), bool)
        assert_type(await client.documents(), list[dict[Any, Any]])
        doc: str = (await client.create_document("d"))["id"]
        assert_type(await client.describe(doc), dict[Any, Any])
        assert_type(await client.document(doc), dict[Any, Any])
        assert_type(await client.put_item(doc, ITEM), dict[Any, Any])
        assert_type(await client.get_item(doc, "a"), dict[Any, Any])
        assert_type(await client.patch_item(doc, "a", {"x1": 2}), dict[Any, Any])
        assert_type(await client.delete_item(doc, "a"), dict[Any, Any])
        assert_type(await client.delete_items(doc, ["a"]), dict[Any, Any])
        assert_type(await client.viewport(doc, BOX, scale=1.0, min_px=1, limit=10), dict[Any, Any])
        assert_type(await client.diff(doc, BOX, BOX, since=1), dict[Any, Any])
        assert_type(await client.search(doc, "word"), dict[Any, Any])
        assert_type(await client.cells(doc, BOX), dict[Any, Any])
        assert_type(await client.import_items(doc, Path("items.ndjson"), replace=True), dict[Any, Any])
        assert_type(await client.import_stream(doc, [b"{}\\n"], gzip=True), dict[Any, Any])
        async for line in client.export_lines(doc):
            assert_type(line, bytes)
        async for item in client.export(doc):
            assert_type(item, dict[Any, Any])
        async with client.stream(doc, scale=1.0) as stream:
            assert_type(stream, AsyncStream)
            assert_type(await stream.view(BOX), dict[Any, Any])
            assert_type(await stream.send(BOX), int)
            assert_type(await stream.receive(1.0), dict[Any, Any] | None)
            async for answer in stream:
                assert_type(answer, dict[Any, Any])
        await client.delete_document(doc)
        await client.aclose()


def synchronously(url: str) -> None:
    with Client(url, token="s3cret") as client:
        assert_type(client, Client)
        assert_type(client.health(), dict[Any, Any])
        assert_type(client.stats(), dict[Any, Any])
        assert_type(client.supports_replace(), bool)
        assert_type(client.documents(), list[dict[Any, Any]])
        doc: str = client.create_document("d")["id"]
        assert_type(client.describe(doc), dict[Any, Any])
        assert_type(client.document(doc), dict[Any, Any])
        assert_type(client.put_item(doc, ITEM), dict[Any, Any])
        assert_type(client.get_item(doc, "a"), dict[Any, Any])
        assert_type(client.patch_item(doc, "a", {"x1": 2}), dict[Any, Any])
        assert_type(client.delete_item(doc, "a"), dict[Any, Any])
        assert_type(client.delete_items(doc, ["a"]), dict[Any, Any])
        assert_type(client.viewport(doc, BOX, scale=1.0, min_px=1, limit=10), dict[Any, Any])
        assert_type(client.diff(doc, BOX, BOX, since=1), dict[Any, Any])
        assert_type(client.search(doc, "word"), dict[Any, Any])
        assert_type(client.cells(doc, BOX), dict[Any, Any])
        assert_type(client.import_items(doc, Path("items.ndjson"), replace=True), dict[Any, Any])
        assert_type(client.import_stream(doc, [b"{}\\n"], gzip=True), dict[Any, Any])
        for line in client.export_lines(doc):
            assert_type(line, bytes)
        for item in client.export(doc):
            assert_type(item, dict[Any, Any])
        with client.stream(doc, scale=1.0) as stream:
            assert_type(stream, Stream)
            assert_type(stream.view(BOX), dict[Any, Any])
            assert_type(stream.send(BOX), int)
            assert_type(stream.receive(1.0), dict[Any, Any] | None)
            for answer in stream:
                assert_type(answer, dict[Any, Any])
        client.delete_document(doc)
        client.close()


try:
    synchronously("http://127.0.0.1:8000")
except VantageError as error:
    assert_type(error.status, int)
"""


def _public_methods(cls: type) -> set[str]:
    return {name for name, value in vars(cls).items() if callable(value) and not name.startswith("_")}


@pytest.mark.slow(seconds=10)  # mypy, cold, in a process of its own
def test_a_users_type_checker_sees_each_client_method_as_what_it_returns(tmp_path):
    for cls in (AsyncClient, Client):
        used = {name for name in _public_methods(cls) if f"client.{name}(" in USER_CODE}
        assert used == _public_methods(cls), f"the code above leaves out some of {cls.__name__}'s methods"
    user = tmp_path / "user.py"
    user.write_text(textwrap.dedent(USER_CODE))
    (tmp_path / "mypy.ini").write_text("[mypy]\n")  # a user's own settings, not this project's
    options = ["--config-file", str(tmp_path / "mypy.ini"), "--strict", "--follow-imports=silent"]
    checked = subprocess.run(
        [sys.executable, "-m", "mypy", *options, "--cache-dir", str(tmp_path / "cache"), str(user)],
        cwd=ROOT,  # where `app` is found, as from a checkout
        capture_output=True,
        text=True,
    )
    assert checked.returncode == 0, checked.stdout + checked.stderr


def test_the_two_clients_have_the_same_methods():
    assert _public_methods(AsyncClient) - {"aclose"} == _public_methods(Client) - {"close"}


@pytest.mark.parametrize("name", sorted(_public_methods(Client) - {"close"}))
def test_the_async_client_takes_what_the_sync_one_takes(name):
    sync, async_ = inspect.signature(getattr(Client, name)), inspect.signature(getattr(AsyncClient, name))
    assert list(async_.parameters.values()) == list(sync.parameters.values())
    assert inspect.iscoroutinefunction(getattr(AsyncClient, name)) == (
        name not in {"export", "export_lines", "stream"}  # an async iterator each, and a stream to enter
    )
