"""``vantage import``: files into a document, in the local store or through a server's API.

Every file is read and checked whole before anything is stored: into the local store, its
items are stored in one transaction (with the snapshot file written first, as the server's
import does); through a server, they are streamed as NDJSON, checked as they are sent, and a
bad record aborts the upload, so the server, whose import is all or nothing, stores nothing.
A document this command created for an import that failed is deleted again.
"""

from __future__ import annotations

import contextlib
import logging
import sys
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from types import ModuleType
from typing import Any

from tqdm import tqdm

from ..config import get_settings
from ..errors import ServiceError
from ..items import Batch, Columns
from . import Source, batches, detect
from .base import ImportFailed

__all__ = ["Group", "import_local", "import_remote", "plan"]


@dataclass
class Group:
    """Files going into one document (named or given by id), as one import."""

    target: str
    files: list[tuple[Source, ModuleType]] = field(default_factory=list)

    @property
    def size(self) -> int:
        return sum(source.size for source, _ in self.files)


def plan(paths: Iterable[Path], doc: str | None, columns: int = 1) -> list[Group]:
    """Every file's format found, before anything is read: with ``doc``, one group of them all;
    without, a group a file, named by its stem.

    :raises ImportFailed: for the first file in no known format
    """
    files = [(Source.of(path, columns=columns), detect(path)) for path in paths]
    if doc is not None:
        return [Group(doc, files)]
    return [Group(_stem(source.path), [(source, module)]) for source, module in files]


def _stem(path: Path) -> str:
    name = path.name.removesuffix(".gz").removesuffix(".GZ")
    return Path(name).stem or name


def _find(documents: list[dict[str, Any]], target: str) -> dict[str, Any] | None:
    """The document whose id, else whose name, is ``target``; None if none.

    :raises ImportFailed: if several documents have that name
    """
    for meta in documents:
        if meta["id"] == target:
            return meta
    named = [meta for meta in documents if meta["name"] == target]
    if len(named) > 1:
        raise ImportFailed(
            f"{len(named)} documents are named {target!r}: give --doc the id of one "
            f"({', '.join(m['id'] for m in named)})"
        )
    return named[0] if named else None


def _read(group: Group, bar: tqdm) -> Iterator[Batch | Columns]:
    """The group's items, batch by batch, moving the progress bar."""
    settings = get_settings()
    items = 0
    for source, module in group.files:
        before = bar.n
        for batch in batches(source, module, settings.max_line_bytes, settings.max_data_bytes):
            items += len(batch)
            elapsed = bar.format_dict["elapsed"] or 1e-9
            bar.set_postfix_str(f"{items:,} items, {items / elapsed:,.0f} items/s", refresh=False)
            bar.update(before + source.done - bar.n)
            yield batch
        bar.update(before + source.size - bar.n)


def _bar(group: Group) -> tqdm:
    return tqdm(
        total=group.size,
        unit="B",
        unit_scale=True,
        unit_divisor=1024,
        desc=group.target,
        file=sys.stderr,
        dynamic_ncols=True,
    )


def _said(group: Group, meta: dict[str, Any], count: int, version: int, replace: bool) -> str:
    files = ", ".join(str(source.path) for source, _ in group.files)
    how = "replacing its items" if replace else "upserted by id"
    return f"{files}: {count:,} items into {meta['name']!r} (id {meta['id']}), version {version}, {how}"


# -- the local store -----------------------------------------------------------------------------


def import_local(groups: list[Group], data_dir: Path, replace: bool) -> list[str]:
    """Import each group into the store at ``data_dir``; a line about each.

    :raises ImportFailed: nothing of that group (and of those after it) stored
    """
    from ..documents import pack
    from ..heap import map_large_blocks
    from ..registry import Registry
    from ..snapfile import SnapshotFiles
    from ..stores import open_store

    map_large_blocks()
    _show_steps()
    settings = get_settings()
    store = open_store(data_dir, settings.database_url)
    files = SnapshotFiles(data_dir / "snapshots", settings.import_bytes)
    registry = Registry(store, files, settings.cache_bytes, settings.max_documents)
    said = []
    try:
        for group in groups:
            for source, _ in group.files:  # decoded beside the store's files, not in a RAM disk
                source.scratch = files.directory
            with _bar(group) as bar:
                table = pack(
                    _read(group, bar), files.directory
                )  # every record checked before anything is stored
            meta = _find(store.documents(), group.target)
            try:
                doc = registry[meta["id"]] if meta is not None else registry.create(group.target)
                count, version = doc.import_table(table, settings.max_items, replace=replace)
            except ServiceError as error:
                raise ImportFailed(f"{group.target}: {error}") from None
            said.append(_said(group, doc.describe(), count, version, replace))
            del table
    finally:
        store.close()
    return said


def _show_steps() -> None:
    """The import's steps after its items are read (merging, building, writing), shown on
    stderr as the store logs them: minutes of silence otherwise, for millions of items."""
    log = logging.getLogger("vantage.import")
    if not log.handlers:
        handler = logging.StreamHandler(sys.stderr)
        handler.setFormatter(logging.Formatter("%(message)s"))
        log.addHandler(handler)
        log.setLevel(logging.INFO)


# -- a server ------------------------------------------------------------------------------------


def import_remote(groups: list[Group], url: str, token: str | None, replace: bool) -> list[str]:
    """Import each group through the server at ``url``, streaming it; a line about each.

    :raises ImportFailed: with the server's reason; nothing of that group stored
    """
    import httpx

    from ..client import Client

    said = []
    with Client(url, token) as client:
        try:
            if replace and not client.supports_replace():
                raise ImportFailed(
                    f"the server at {url} cannot replace a document's items (its import route has no "
                    "mode=replace): import without --replace to upsert by id, delete the document "
                    "first, or import into the local store (no --url)"
                )
            for group in groups:
                meta = _find(client.documents(), group.target)
                created = meta is None
                if meta is None:
                    meta = client.create_document(group.target)
                try:
                    with _bar(group) as bar:
                        chunks = (batch.lines() for batch in _read(group, bar))
                        answer = client.import_stream(meta["id"], chunks, replace=replace)
                except BaseException:
                    if created:
                        _quietly(client.delete_document, meta["id"])
                    raise
                said.append(_said(group, meta, answer["imported"], answer["version"], replace))
        except httpx.HTTPStatusError as error:
            raise ImportFailed(f"the server at {url} refused: {_detail(error.response)}") from None
        except httpx.TransportError as error:
            raise ImportFailed(f"cannot talk to the server at {url} ({error!r}): is it running?") from None
    return said


def _detail(response: Any) -> str:
    try:
        detail = response.json()["detail"]
    except Exception:
        detail = response.text[:500]
    fix = {401: " (give --token)", 403: " (this token may not write)"}.get(response.status_code, "")
    return f"{response.status_code} {detail}{fix}"


def _quietly(call: Any, *args: Any) -> None:
    with contextlib.suppress(Exception):
        call(*args)
