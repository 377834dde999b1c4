"""The process's own upkeep, apart from the domain: compiling the kernels before the first
request, and keeping start-up's objects out of the garbage collector's way (the heap's
upkeep is ``heap``'s)."""

import contextlib
import gc
import importlib
import logging
import os
import pickle
import sys
import tempfile
import time
from collections.abc import Callable, Iterator
from functools import partial
from pathlib import Path
from typing import Any

import numba
import numpy as np
import xxhash
from numba.core.dispatcher import Dispatcher

import spatial

from . import editfile
from .documents import pack
from .items import Item, batch_of
from .looks import band_json
from .masks import masks
from .packed import scratch_in_files
from .search import search
from .snapfile import load, save, write_base
from .snapshots import Snapshot, build
from .table import Edit, ItemTable

__all__ = ["LISTED_SUFFIX", "Listed", "compiles_said", "freeze_start_up_objects", "warm_up"]

log = logging.getLogger("vantage")

_say = partial(print, flush=True)


def warm_up(say: Callable[[str], object] = _say) -> None:
    """Load or compile the hot kernels now, not on a client's first request. A wheel ships them
    compiled (``deploy/build_backend.py``). What numba's cache lacks (a plain wheel, a
    checkout, another numba) is compiled, which takes a minute or two: said, as
    ``compiles_said`` says it. The warm-up's work (``_compile``) calls each kernel as requests
    do; once it has run for this code, the kernels it called are listed (``Listed``) and later
    starts load them by the list: ~0.6 s, where the work took ~2."""
    with compiles_said(f"worker {os.getpid()}", say):
        listed = Listed.here()
        if not listed.load():
            _compile()
            listed.save()


class Listed:
    """The kernels the warm-up's work calls, each with the signatures it was called with, in a
    file in ``app/__pycache__`` named for all they depend on: the sources of ``app`` and
    ``spatial``, numba's version, Python's (as numba's cache tags it) and the CPU compiled for
    (a change to any is another file, and the work runs again). Loading a kernel by its
    signature (``Dispatcher.compile``: from numba's cache, else compiled) is what the work's
    call did, without the work's builds, saves and imports."""

    def __init__(self, path: Path) -> None:
        self.path = path

    @classmethod
    def here(cls) -> "Listed":
        digest = xxhash.xxh3_64()
        for package in _PACKAGES:
            for source in sorted(package.rglob("*.py")):
                digest.update(source.relative_to(package.parent).as_posix().encode() + b"\0")
                digest.update(source.read_bytes())
        cpu = getattr(numba.config, "CPU_NAME", None)
        digest.update(f"{numba.__version__} {sys.implementation.cache_tag} {cpu}".encode())
        return cls(Path(__file__).parent / "__pycache__" / f"warm-up-{digest.hexdigest()}{LISTED_SUFFIX}")

    def load(self) -> bool:
        """Load (or compile) every kernel listed; False when there is no list for this code."""
        try:
            for module, name, signature in pickle.loads(self.path.read_bytes()):  # written by save()
                getattr(importlib.import_module(module), name).compile(signature)
        except FileNotFoundError:
            return False
        except Exception as error:  # a torn list, or one this code cannot take: the work instead
            log.warning(
                "the warm-up's list of kernels %s cannot be used (%r): calling them instead", self.path, error
            )
            return False
        return True

    def save(self) -> None:
        """List the kernels called so far (those of this file's name replace any other list);
        nothing where the directory cannot be written (an install read-only)."""
        listed = [
            (module, name, signature)
            for module, name, kernel in _loaded_kernels()
            for signature in kernel.signatures
        ]
        written = self.path.with_name(f".{self.path.name}.{os.getpid()}")
        try:
            self.path.parent.mkdir(exist_ok=True)
            for stale in self.path.parent.glob(f"warm-up-*{LISTED_SUFFIX}"):
                if stale != self.path:  # another version's
                    stale.unlink(missing_ok=True)
            written.write_bytes(pickle.dumps(listed))
            written.replace(self.path)  # whole or not at all, for a start beside this one
        except OSError as error:
            written.unlink(missing_ok=True)
            log.info(
                "the warm-up's list of kernels was not written (%s): the next start calls them again", error
            )


#: The name's end of the file of ``Listed`` (the wheel's build packs it with numba's cache).
LISTED_SUFFIX = ".kernels"
_PACKAGES = (Path(__file__).parent, Path(spatial.__file__).parent)


def _loaded_kernels() -> Iterator[tuple[str, str, Dispatcher]]:
    """``(module, name, kernel)`` of each compiled function the modules of ``app`` and
    ``spatial`` imported so far define."""
    for module_name, module in list(sys.modules.items()):
        if module_name.partition(".")[0] not in ("app", "spatial"):
            continue
        for name, kernel in list(vars(module).items()):
            if isinstance(kernel, Dispatcher) and kernel.py_func.__module__ == module_name:
                yield module_name, name, kernel


@contextlib.contextmanager
def compiles_said(who: str, say: Callable[[str], object] = _say) -> Iterator[None]:
    """Within it, ``say`` says when numba starts compiling kernels its cache lacks (a kernel
    loaded from the cache is no compile), and at the end how many it compiled, how long it
    took: the minute or two a checkout's first run spends, not a silence."""
    compiles = _Compiles(who, say)
    with numba.core.event.install_listener("numba:compile", compiles):
        yield
    if compiles.count:
        took = time.monotonic() - compiles.started
        say(f"{who}: {compiles.count} kernels compiled in {took:.0f} s; numba's cache holds them now")


class _Compiles(numba.core.event.Listener):
    """Counts the kernels numba compiles, and says so at the first."""

    def __init__(self, who: str, say: Callable[[str], object]) -> None:
        self.who, self.say, self.count, self.started = who, say, 0, 0.0

    def on_start(self, event: numba.core.event.Event) -> None:
        if not self.count:
            self.started = time.monotonic()
            self.say(
                f"{self.who}: compiling the index's kernels, which numba's cache lacks "
                "(once after an install from source or a numba upgrade; a minute or two) ..."
            )
        self.count += 1

    def on_end(self, event: numba.core.event.Event) -> None:
        pass


def _compile() -> None:
    """Query, diff, join and search a small snapshot as an import builds it and as it is
    mapped from its file: the mapped arrays are read-only, which numba compiles code of its
    own for (~9 s that the first import after an install paid, holding every request up, and
    1.5 s the first search)."""
    boxes = np.array([[0.0, 0.0, 1.0, 1.0], [2.0, 2.0, 3.0, 3.0]])
    table = ItemTable.merge(
        [ItemTable.of(["a", "b"], boxes, [b'{"kind":"word","data":{"text":"a word"}}', b"{}"])]
    )
    ItemTable.merge([table, ItemTable.of(["a"], boxes[:1], [b"{}"])])  # an upsert: "a" back to its place
    table.position("a")
    built = build(table, 1, "warm-up")
    _answer(built)
    # A scratch file: where there is nowhere to write one, first use compiles these instead.
    # Every scratch array in a file first, as a large import's are (their kernels take other
    # paths), then as a small one's: in memory
    for scratch in (scratch_in_files, contextlib.nullcontext):
        with contextlib.suppress(OSError), tempfile.TemporaryDirectory() as directory, scratch():
            _in_files(Path(directory), built)
    for corner in _CORNERS[1:]:  # as a compaction builds
        build(ItemTable.of(["a", "b", "c"], np.array(_boxes(corner)), [b"{}"] * 3), 1, "warm-up")


def _in_files(directory: Path, built: Snapshot) -> None:
    """``built`` saved in ``directory``, mapped, answered, folded with an edit and opened with
    it saved beside; and imports of three items written there."""
    path = directory / "warm-up.snapshot"
    save(built, path)
    mapped = load(path, "warm-up", 1)
    _answer(mapped)
    # ... and folded with an edit, as a compaction does (its fold reads the file's rank)
    edit = ("b", 2, (5.0, 5.0, 6.0, 6.0), b"{}")
    mapped.document_table(directory, [edit])
    # ... and with the edit saved beside it and made again, as an open takes it
    stored = _OneEdit(edit)
    editfile.save(path.with_suffix(".vedits"), mapped.with_edits([edit])[0], stored, "warm-up")
    restored = editfile.load(path.with_suffix(".vedits"), mapped, 2, stored, "warm-up")
    assert restored is not None
    _answer(restored)
    del mapped, restored  # the file's mapping, before its directory goes
    for corner in _CORNERS:
        imported = _packed(directory, corner)  # as an import packs a file's items
        write_base(imported, path, 2, "warm-up")
        del imported  # its spilled bodies' mapping, too


class _OneEdit:
    """A store's reads (``editfile.Stored``) of a document edited once since its base, by ``edit``."""

    def __init__(self, edit: Edit) -> None:
        self.edit = edit

    def document(self, doc_id: str) -> dict[str, Any]:
        return {"id": doc_id, "version": self.edit[1]}

    def edits(self, doc_id: str, after: int = 0) -> list[Edit]:
        return [self.edit] if self.edit[1] > after else []

    def last_edits(self, doc_id: str, upto: int, count: int) -> list[Edit]:
        return [self.edit][:count] if self.edit[1] <= upto else []


# The far corner of a warm-up's scenes of three tiny items: near, then spanning past 32 bits of
# the overview's cells on each axis (a country's buildings, say), and on one axis alone. Their
# bands sort keys of 32 and 64 bits and cells of 32 and 64 (``overview._build._cell_order``).
_CORNERS = ((2.0, 2.0), (2.0**40, 2.0**40), (2.0**40, 0.0))


def _boxes(corner: tuple[float, float]) -> list[tuple[float, float, float, float]]:
    x, y = corner
    return [(0.0, 0.0, 1.0, 1.0), (x, y, x + 1.0, y + 1.0), (x, 0.0, x + 1.0, 1.0)]


def _packed(spill: Path, corner: tuple[float, float]) -> ItemTable:
    """Three items packed as an import packs a file's, spilled to ``spill``."""
    items = [Item(name, *box) for name, box in zip("abc", _boxes(corner), strict=True)]
    return pack([batch_of(items, 64)], spill)


def _answer(snap: Snapshot) -> None:
    """What requests do with a snapshot's compiled code, once each."""
    tree, overview = snap.tree, snap.overview
    assert overview is not None and snap.looks is not None
    edited = tree.copy()  # as edits leave a tree: its walks, compiled apart, scan them too
    edited.insert(-1, (0.0, 0.0, 1.0, 1.0))  # a position's id is never negative
    for walked in (tree, edited):
        walked.query((0, 0, 1, 1), min_size=0.5)
        walked.diff((0, 0, 1, 1), (1, 1, 3, 3))
    snap.items_array(tree.query((0, 0, 3, 3)))
    snap.ids_array(tree.query((0, 0, 3, 3)))  # a diff's leave list: ids are packed, bodies framed
    band_json(overview, snap.looks.names, overview.lo)
    aggregates = overview.query(overview.lo, (0, 0, 3, 3))
    masks(snap, overview.lo, aggregates, (1.0, 0, 0))  # an aggregate's pixels, drawn
    search(snap, "word", 1)


def freeze_start_up_objects() -> None:
    """Leave the objects made so far (modules, compiled kernels: ~140k in a worker) out of
    the garbage collector's full passes, which otherwise took ~80 ms scanning them: a stall
    on whichever request or pushed edit was under way. They live as long as the process.
    Call it before the process makes objects that may die (documents, requests)."""
    gc.collect()  # what start-up left as garbage is freed, not kept for good
    gc.freeze()
