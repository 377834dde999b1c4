"""A document's snapshot: one version, immutable, that queries run on; built from an item
table (or mapped from a snapshot file, see ``snapfile``), and edited copy-on-write.

Tree ids are positions into the table (then past it, for items edits created), so a snapshot
answers with packed JSON joined in compiled code, not Python objects.
"""

from __future__ import annotations

import uuid
from bisect import bisect_right
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field, replace
from functools import cached_property
from pathlib import Path

import msgspec
import numpy as np
from immutables import Map, MapMutation

from spatial import QuadTree
from spatial.overview import Overview
from spatial.sorting import found_in

from .blocks import Blocks
from .folding import folded
from .frames import Framed
from .looks import Looks, agg_id, agg_json, band_json
from .table import Edit, ItemTable, Packed
from .text import TextIndex, piece_of

__all__ = ["COMPACT_AFTER", "Edit", "EditLog", "LOG_LIMIT", "Snapshot", "build", "new_base_id"]

LOG_LIMIT = 100_000  # edits remembered for catching clients up; beyond, they start over
RELEASE_AFTER = 64  # edits applied at once between two hand-backs of the base file's pages they mapped
COMPACT_AFTER = 1024  # edits since the base (plus one per 256 items) before they are folded into a new one


@dataclass
class EditLog:
    """The version and item id of every edit after a base, in two lists (no object an entry:
    an open takes 100k of them from its saved edits): shared and append-only, so a snapshot
    reads only the entries up to its own version."""

    versions: list[int] = field(default_factory=list)
    ids: list[str] = field(default_factory=list)

    def __len__(self) -> int:
        return len(self.versions)

    def upto(self, version: int) -> int:
        """How many entries are of ``version`` or before."""
        return bisect_right(self.versions, version)


@dataclass(frozen=True)
class Snapshot:
    """One version of a document. Tree ids are positions into ``table``, then into edits."""

    version: int
    tree: QuadTree
    table: ItemTable  # the items as loaded or imported; shared between snapshots, never mutated
    # What edits changed since the base, in persistent maps: an edit's snapshot shares them with
    # the one before but for its own changes, so it costs O(log edits), not a copy of them all
    overlay: Map[int, tuple[bytes, bytes]] = field(default_factory=Map)  # pos -> (JSON id, body) by edits
    added: Map[str, int] = field(default_factory=Map)  # ids first created by edits
    log: EditLog = field(default_factory=EditLog)  # every edit after version ``base``
    base: int = 0
    next_position: int = -1  # where an edit puts the next new item; never reused
    # What stands in for items too small to draw, per zoom band, and the kinds and z it was built from
    overview: Overview | None = None
    looks: Looks | None = None
    # Each band's aggregates as built, as JSON, made on first use; shared by the snapshots of
    # one build (edits change a few aggregates, which are encoded apart)
    agg_bodies: dict[int, Packed] = field(default_factory=dict)
    base_id: str | None = None  # the name of the base it was built from (its file's)
    size: int = 0  # bytes of the base: mapped from its file, or built in memory
    edits: int = 0  # edits applied since the base
    text: TextIndex | None = None  # the base's text items' folded texts, for search
    removed: Map[int, None] = field(default_factory=Map)  # positions deleted by edits since the base (keys)
    blocks: Blocks | None = None  # the base's file's blocks, when mapped from one
    # A file lays the base's items out in its tree's order (a screen's items lie together in
    # it, not scattered): each position's place in document order, the import's, when they do
    rank: np.ndarray | None = None

    @classmethod
    def base_of(
        cls,
        table: ItemTable,
        tree: QuadTree,
        overview: Overview,
        looks: Looks,
        text: TextIndex,
        version: int,
        base_id: str | None,
        size: int,
        blocks: Blocks | None = None,
        rank: np.ndarray | None = None,
    ) -> Snapshot:
        """A fresh base at ``version``, no edits: built (``build``) or mapped from its file
        (whose ``blocks`` are checked as they are first read, and whose items' places in
        document order are ``rank``)."""
        # The document folds its edits into a new base (in the background) before the tree
        # would rebuild itself in an edit: at 1e8 items that would take a minute and GBs.
        tree.max_buffered = 2 * _compact_after(len(table))
        return cls(
            version,
            tree,
            table,
            base=version,
            overview=overview,
            looks=looks,
            base_id=base_id,
            size=size,
            text=text,
            blocks=blocks,
            rank=rank,
        )

    def __post_init__(self) -> None:
        if self.next_position < 0:
            object.__setattr__(self, "next_position", len(self.table))

    def item_id(self, pos: int) -> str:
        edit = self.overlay.get(pos)
        return msgspec.json.decode(edit[0]) if edit else self.table.item_id(pos)

    def item_json(self, pos: int) -> bytes | memoryview:
        edit = self.overlay.get(pos)
        return edit[1] if edit else self.table.bodies[pos]

    def items_array(self, positions: np.ndarray, ends: tuple[bytes, bytes] = (b"[", b"]")) -> bytes:
        """The JSON array of the items at ``positions`` (``ends``: it and what comes around it)."""
        return self._array(positions, self.table.bodies, 1, ends=ends)

    def entries_array(
        self,
        positions: np.ndarray,
        band: int | None,
        aggregates: np.ndarray,
        ends: tuple[bytes, bytes] = (b"[", b"]"),
        masks: Sequence[bytes] | None = None,
    ) -> bytes:
        """The JSON array of the items at ``positions`` and of ``band``'s ``aggregates`` (``ends``:
        it and what comes around it); with ``masks``, each aggregate's ``"mask"`` member (one a
        aggregate, in order; empty: none)."""
        if band is None or not len(aggregates):
            return self._array(positions, self.table.bodies, 1, ends=ends)
        overview, looks = self.overview, self.looks
        assert overview is not None and looks is not None  # aggregates come from the overview
        names = looks.names
        bodies = self.agg_bodies.get(band)
        if bodies is None:
            bodies = self.agg_bodies[band] = band_json(overview, names, band)
        edited = overview.edited(band, aggregates) | (aggregates >= len(bodies))
        if masks is not None:  # one by one: each with its mask
            changed = iter(agg_json(overview, names, band, aggregates[edited]) if edited.any() else [])
            more = []
            for index, is_edited, mask in zip(aggregates.tolist(), edited.tolist(), masks, strict=True):
                body = next(changed) if is_edited else bytes(bodies[index])
                more.append(body[:-1] + b"," + mask + b"}" if mask else body)
            return self._array(positions, self.table.bodies, 1, more, ends=ends)
        more = agg_json(overview, names, band, aggregates[edited]) if edited.any() else []
        built = aggregates[~edited]
        if len(built):
            more.append(bodies.join(built))
        return self._array(positions, self.table.bodies, 1, more, ends=ends)

    def item_boxes(self, positions: np.ndarray) -> np.ndarray:
        """The boxes of the items at ``positions``, (n, 4): the table's, or an edit's."""
        table = self.table.read_boxes()
        inside = positions < len(table)
        out = np.empty((len(positions), 4))
        out[inside] = table[positions[inside]]
        edited = ~inside
        if self.overlay:
            edited |= self._edited(positions)
        for i in np.flatnonzero(edited).tolist():
            out[i] = self.tree.get(int(positions[i]))
        return out

    def ndjson(self, positions: np.ndarray) -> bytes:
        """The items at ``positions`` as NDJSON lines (an import takes them back as they are)."""
        return (
            self._array(positions, self.table.bodies, 1, sep=b"\n", ends=(b"", b"\n"))
            if len(positions)
            else b""
        )

    def ids_array(self, positions: np.ndarray, more: Sequence[bytes] = ()) -> bytes:
        """The JSON array of the ids at ``positions``, then of the JSON strings ``more``."""
        return self._array(positions, self.table.ids, 0, more)

    def _array(
        self,
        positions: np.ndarray,
        packed: Packed | Framed,
        field: int,
        more: Sequence[bytes] = (),
        sep: bytes = b",",
        ends: tuple[bytes, bytes] = (b"[", b"]"),
    ) -> bytes:
        if self.overlay:  # edited items come from the overlay, the rest from the table
            edited = self._edited(positions)
            more = [*more, *(self.overlay[p][field] for p in positions[edited].tolist())]
            positions = positions[~edited]
        if not more:  # the common answer: one join, its ends written with it
            return packed.join(positions, sep, ends)
        parts = [packed.join(positions, sep)] if len(positions) else []
        return ends[0] + sep.join(parts + list(more)) + ends[1]

    @cached_property
    def search_index(self) -> TextIndex:
        """The folded texts of the live text items, in document order: the base's, with the
        edits since laid over it (once per snapshot, on its first search)."""
        base = self.text if self.text is not None else TextIndex.build(())
        if self.blocks is not None and self.text is not None:
            self.blocks.check(*self.text.to_arrays().values())
        if not self.overlay and not self.removed:
            return base
        changed = {pos: piece_of(body) for pos, (_, body) in self.overlay.items() if pos not in self.removed}
        return base.with_edits(changed, self.removed, self._place)

    def in_document_order(self, positions: np.ndarray) -> np.ndarray:
        """``positions`` in document order: the base's items as imported, then those edits
        created, as they were."""
        if self.rank is None:
            return np.sort(positions)
        if self.blocks is not None:
            self.blocks.check(self.rank)
        base = positions < len(self.rank)
        places = positions.copy()
        places[base] = self.rank[positions[base]]
        return positions[np.argsort(places, kind="stable")]

    def _place(self, pos: int) -> int:
        """Where position ``pos`` comes in document order (see ``in_document_order``)."""
        if self.rank is None or pos >= len(self.rank):
            return pos
        if self.blocks is not None:
            self.blocks.check(self.rank[pos : pos + 1])  # its block alone
        return int(self.rank[pos])

    def unpacked(self, spill: Path | None = None) -> Snapshot:
        """This snapshot with its base's bodies in one buffer, each frame decompressed once
        (with ``spill``, a directory: into a file there): for a pass over every item in
        document order (an export), where a frame laid out in the tree's order holds items
        from all over the document."""
        bodies = self.table.bodies.unpacked(spill)
        if bodies is self.table.bodies:
            return self
        table = replace(self.table, bodies=bodies)
        if "_index" in self.table.__dict__:  # the cached_property's slot: the ids are the same
            table.__dict__["_index"] = self.table._index
        return replace(self, table=table)

    def document_table(self, spill: Path | None = None, edits: Sequence[Edit] = ()) -> ItemTable:
        """The base's table in document order, with ``edits`` (the store's since the base)
        applied as the store applies them (``folded``): the table itself when it is
        in that order and there are none, else a copy (with ``spill``, a directory: its bodies
        in a file there). What an import merges with and the store keeps: the document's
        order is the import's.

        :raises SnapshotCorrupt: if a block of the base's file is bad
        """
        if self.rank is None and not edits:
            return self.table
        if self.blocks is not None and self.rank is not None:
            self.blocks.check(self.rank)
        return folded(self.table, edits, self.rank, spill)

    def _edited(self, positions: np.ndarray) -> np.ndarray:
        """Which of ``positions`` edits changed, a bool each: a search of the sorted positions
        edited, not ``np.isin``, which sorted them all again on every answer (3 ms of a
        viewport's 5 ms with 35,000 edits pending)."""
        return found_in(self._edited_positions, positions)[1]

    @cached_property
    def _edited_positions(self) -> np.ndarray:
        """The positions edits changed, sorted (once a snapshot, at its first answer)."""
        return np.sort(np.fromiter(self.overlay, np.int64, len(self.overlay)))

    @property
    def needs_compaction(self) -> bool:
        """Whether enough edits piled up since the base to fold them into a new one."""
        return self.edits > _compact_after(len(self.table))

    @property
    def broken(self) -> str | None:
        """Why the base's file is corrupt, once a read found a bad block (then the document is
        rebuilt from the store: see ``Document.refresh``); None while it is sound."""
        return self.blocks.bad if self.blocks is not None else None

    def position(self, item_id: str) -> int | None:
        """The live position of ``item_id``, or None."""
        return _position(item_id, self.table.position, self.added, self.tree)

    def stored_table(self, spill: Path | None = None) -> ItemTable | None:
        """The table in document order (``document_table``), when it is all the store holds
        (no edit since the import that built it): an import then merges with it instead of
        reading a second copy from the store."""
        fresh = not self.overlay and len(self.tree) == len(self.table)
        return self.document_table(spill) if fresh else None

    @property
    def bounds(self) -> tuple[float, float, float, float] | None:
        return self.tree.bounds

    def with_edits(self, edits: Iterable[Edit]) -> tuple[Snapshot, list[str]]:
        """This snapshot with ``edits`` applied, ``(item id, version, box, body)`` each (box and
        body None: deleted), oldest first; and the ids changed: the items' and the aggregates'.
        The one place edits are applied: a client's, and those another process stored.
        Deleting an item that is not there changes nothing (the store keeps only each item's
        last edit, so one created and deleted since the base comes as a deletion alone).
        Cost: O(log n) an edit, whatever the edits pending (the maps of what was edited are
        persistent, the tree's tombstones and insert buffer shared).
        """
        assert self.overview is not None and self.looks is not None  # both built with the base
        tree, overview = self.tree.copy(), self.overview.copy()
        looks = self.looks
        added, overlay, removed = self.added.mutate(), self.overlay.mutate(), self.removed.mutate()
        nxt, version, changed, logged, applied = self.next_position, self.version, [], [], 0
        edits = list(edits)
        named = list(dict.fromkeys(item_id for item_id, *_ in edits))
        found = dict(zip(named, self.table.positions(named), strict=True))  # the table's: edits leave it
        for item_id, edit_version, box, body in edits:
            if applied and not applied % RELEASE_AFTER and self.blocks is not None:  # an open catching up
                self.blocks.release()
            applied += 1
            version = max(version, edit_version)
            pos = _position(item_id, found.__getitem__, added, tree)  # as the edits so far left it
            aggs: set[tuple[int, int]] = set()
            if pos is not None:
                aggs = overview.remove(pos, tree.get(pos))
            if body is None:
                if pos is None:  # created and deleted since the base: the store keeps only the last
                    continue
                tree.remove(pos)
                removed[pos] = None
            else:
                assert box is not None  # an edit's box and body are None together: a delete
                if pos is None:
                    pos, nxt = nxt, nxt + 1
                    added[item_id] = pos
                    tree.insert(pos, box)
                else:
                    tree.update(pos, box)
                looks = looks.with_item(body)
                aggs |= overview.insert(pos, box, *looks.of_body(body))
                overlay[pos] = (msgspec.json.encode(item_id), body)
            ids = [item_id, *map(agg_id, sorted(aggs))]
            changed += ids
            logged += [edit_version] * len(ids)
        if applied >= RELEASE_AFTER and self.blocks is not None:  # (the last run's too)
            self.blocks.release()
        log, base = self.log, self.base
        if len(log) + len(changed) > LOG_LIMIT:  # start over: clients further behind get a reset
            log, base = EditLog(), self.version
        if len(changed) > LOG_LIMIT:  # these alone are past it (an open catching up): from their end
            base = version
        else:  # unseen by older snapshots: they read up to their own version
            log.versions += logged
            log.ids += changed
        snap = replace(
            self,
            version=version,
            tree=tree,
            overview=overview,
            looks=looks,
            added=added.finish(),
            overlay=overlay.finish(),
            removed=removed.finish(),
            next_position=nxt,
            log=log,
            base=base,
            edits=self.edits + applied,
        )
        return snap, changed

    def edited_since(self, version: int) -> list[str] | None:
        """Ids edited after ``version`` up to this snapshot; None when the log does not reach
        back that far (an import since, or an old version), so the caller must start over.

        :raises ValueError: if ``version`` is newer than this snapshot
        """
        if version > self.version:
            raise ValueError(f"version {version} is newer than the document's version {self.version}")
        if version < self.base:
            return None
        return list(dict.fromkeys(self.log.ids[self.log.upto(version) : self.log.upto(self.version)]))


def _position(
    item_id: str,
    in_table: Callable[[str], int | None],
    added: Map[str, int] | MapMutation[str, int],
    tree: QuadTree,
) -> int | None:
    """Where ``item_id`` lives: created by an edit, else in the table (``in_table``: its
    position there); None if not in ``tree``."""
    pos = added.get(item_id)
    if pos is None:
        pos = in_table(item_id)
    return pos if pos is not None and pos in tree else None


def _compact_after(items: int) -> int:
    return COMPACT_AFTER + items // 256


def new_base_id() -> str:
    """A name for a new base: never given to another."""
    return uuid.uuid4().hex


def build(table: ItemTable, version: int, base_id: str | None) -> Snapshot:
    """The snapshot of ``table`` at ``version``: the tree, the overview and the looks built."""
    bodies = table.bodies.unpacked()  # a table read or merged: in one buffer already
    looks, kinds, z = Looks.of(bodies)
    text = TextIndex.of_table(bodies)
    bodies.release()  # read through once: a spilled import's bodies go back to the page cache
    overview = Overview.build(table.boxes, kinds, z)
    tree = QuadTree.bulk_load(table.boxes)
    parts = [
        table.ids.array,
        table.ids.offsets,
        bodies.array,
        bodies.offsets,
        table.boxes,
        *table._index,
        *tree.to_arrays().values(),
        *overview.to_arrays().values(),
        *text.to_arrays().values(),
    ]
    size = sum(a.nbytes for a in parts)
    return Snapshot.base_of(table, tree, overview, looks, text, version, base_id, size)
