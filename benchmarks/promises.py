"""Does every promise of the Guarantees (docs/guarantees.md) fail a test when it breaks? Each promise has one
or more small, realistic mutants of the code that keeps it; each mutant is applied alone in a
scratch copy of the checkout and the tests that promise names are run against it. A mutant the
tests miss is a promise nothing guards.

Run from the repository root (run by hand, not in CI: ~15-30 minutes)::

    .venv/bin/python -m benchmarks.promises                 # every mutant
    .venv/bin/python -m benchmarks.promises --only search,token   # those whose words match
    .venv/bin/python -m benchmarks.promises --list

The copy's numba cache is a directory of its own, so a mutated kernel is compiled from its
mutated source (the first run compiles everything: a minute or two). Prints a table: promise,
mutant, caught or missed, seconds; exits non-zero if any mutant was missed.
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
TIMEOUT = 600  # seconds a mutant's tests may run (a hang is caught: the tests did not pass)


@dataclass(frozen=True)
class Mutant:
    promise: str  # the Guarantees bullet, as its bold words start
    what: str  # the break, in words
    path: str  # the file it changes
    old: str  # text that occurs exactly once in it...
    new: str  # ...and what it becomes
    tests: tuple[str, ...]  # what pytest runs (the tests the promise names)


MUTANTS = [
    Mutant("Writes need a token", "a wrong static token is taken for full access", "app/access.py",
           "        raise Forbidden(UNKNOWN)", "        return FULL",
           ("tests/test_access.py::test_writes_need_a_token_and_a_refused_one_changes_nothing",)),
    Mutant("Writes need a token", "PATCH treated as a read", "app/guard.py",
           'SAFE = frozenset({"GET", "HEAD", "OPTIONS"})', 'SAFE = frozenset({"GET", "HEAD", "OPTIONS", "PATCH"})',
           ("tests/test_access.py",)),
    Mutant("Signed access tokens", "a read grant writes", "app/access.py",
           '"write" in (self.docs.get(doc), self.docs.get("*"))', "doc in self.docs or \"*\" in self.docs",
           ("tests/test_signed_tokens.py",)),
    Mutant("Signed access tokens", "exp not required", "app/access.py",
           'options={"require": ["exp"], ', "options={",
           ("tests/test_signed_tokens.py",)),
    Mutant("Signed access tokens", "a token verified while valid keeps reading and writing after its exp",
           "app/access.py",
           "            if granted.expired:  # verified while valid, then cached: its `exp` still counts\n"
           "                raise Unauthorized(EXPIRED)\n", "",
           ("tests/test_signed_tokens.py::test_an_expired_signed_token_is_401_also_one_verified_and_cached_while_valid",)),
    Mutant("Signed access tokens", "the wildcard's write not read: only the document's own entry",
           "app/access.py", '"write" in (self.docs.get(doc), self.docs.get("*"))', 'self.docs.get(doc) == "write"',
           ("tests/test_signed_tokens.py::test_the_wildcard_write_grant_writes_every_document",)),
    Mutant("Signed access tokens", "the secret's bound halved (16-byte secrets accepted)", "app/access.py",
           "MIN_SECRET_BYTES = 32  #", "MIN_SECRET_BYTES = 16  #",
           ("tests/test_signed_tokens.py::test_a_short_secret_or_a_bad_key_stops_the_server_at_start_saying_which",
            "tests/test_signed_tokens.py::test_vantage_token_refuses_a_secret_the_server_refuses_in_the_servers_words")),
    Mutant("Signed access tokens", "any truthy `create` claim (\"no\") may create", "app/access.py",
           'create=claims.get("create") is True,', 'create=bool(claims.get("create")),',
           ("tests/test_signed_tokens.py::test_creating_needs_the_claim_create_true_exactly",)),
    Mutant("Hostile requests hold nothing", "a gzip body read whole before its cap", "app/routers/documents.py",
           "        if size is None or size < 0:", "        if False:",
           ("tests/test_attacks.py::test_a_gzip_body_is_refused_as_it_inflates_past_the_cap_never_after",)),
    Mutant("Hostile requests hold nothing", "a missing document's lock kept", "app/registry.py",
           "        finally:  # opened or not (no such document): nothing of the id is kept\n            with self._lock:\n                self._opening.pop(doc_id, None)",
           "        finally:\n            if doc_id in self._open:\n                self._opening.pop(doc_id, None)",
           ("tests/test_attacks.py::test_requests_for_documents_that_do_not_exist_leave_nothing_in_memory",)),
    Mutant("Only this machine's pages", "any Host header answered", "app/guard.py",
           'if self.hosts is not None and _hostname(host) not in self.hosts and path != "/health":',
           "if False:",
           ("tests/test_access.py",)),
    Mutant("Nothing is read before it is allowed", "a growing body's running cap removed", "app/guard.py",
           "            if size > limit:\n                raise too_large", "            pass",
           ("tests/test_access.py", "tests/test_attacks.py::test_no_body_is_read_before_the_token_or_past_its_limit_or_its_time")),
    Mutant("Limits say which limit", "the items limit unnamed", "app/documents.py",
           "the most is {max_items} (VANTAGE_MAX_ITEMS)", "the most is {max_items}",
           ("tests/test_access.py::test_limits_are_named_with_their_setting",)),
    Mutant("No answer is unbounded", "the client's limit not capped", "app/config.py",
           "return min(limit or self.default_limit, self.max_limit)", "return limit or self.default_limit",
           ("tests/test_attacks.py::test_no_answer_lists_more_ids_leaving_than_the_limit", "tests/test_service.py")),
    Mutant("The stream answers the newest viewport", "a queued viewport kept, a newer one dropped", "app/session.py",
           '            self.latest = Job("view", message.seq, view, self.settings.cap(message.limit))',
           '            self.latest = self.latest or Job("view", message.seq, view, self.settings.cap(message.limit))',
           ("tests/test_promises.py", "tests/test_panning.py::test_a_newer_viewport_supersedes_queued_ones")),
    Mutant("One document's writes never stall", "writers wait in threads, not on the event loop", "app/documents.py",
           "        async with self._writing, self.store.turn:\n            return await run_in_threadpool(edit, *args)",
           "        return await run_in_threadpool(edit, *args)",
           ("tests/test_attacks.py::test_one_documents_writes_never_stall_another_documents_readers",)),
    Mutant("An import of any size, in parts", "a missing part not noticed", "app/uploads.py",
           "        if missing or extra:", "        if extra:", ("tests/test_uploads.py",)),
    Mutant("An import of any size, in parts", "a refused commit loses the upload", "app/uploads.py",
           "            (self._aside / \"owner\").unlink()\n            os.rename(self._aside, self._home)",
           "            (self._aside / \"owner\").unlink()", ("tests/test_uploads.py",)),
    Mutant("An import of any size, in parts", "an import holds its bodies in memory", "app/documents.py",
           "    if spill is None:\n        tables =", "    if True:\n        tables =",
           ("tests/test_import_memory.py",)),
    Mutant("An import of any size, in parts", "a merge's spill loses a byte a step", "app/table.py",
           "out.write(memoryview(self.buffer)[step : min(step + STEP_BYTES, hi)])",
           "out.write(memoryview(self.buffer)[step : min(step + STEP_BYTES - 1, hi)])",
           ("tests/test_documents.py::test_a_merge_spilled_to_disk_is_the_merge_in_memory",)),
    Mutant("A working set, one version", "the blocks a join read are not checked before it answers",
           "app/table.py", "        if watch is not None and pending[0]:\n            watch.settle()\n        return out.tobytes()",
           "        return out.tobytes()", ("tests/test_snapshot_blocks.py",)),
    Mutant("A working set, one version", "a bad block among checked ones passes the quick test",
           "app/blocks.py", "if marks.min() == marks.max() == CHECKED:", "if marks.min() == CHECKED:",
           ("tests/test_snapshot_blocks.py",)),
    Mutant("A working set, one version", "a walk reports no block it read", "spatial/_kernels.py",
           "        if marks[b] != 1:\n            marks[b] |= 2", "        if False:\n            marks[b] |= 2",
           ("tests/test_snapshot_blocks.py",)),
    Mutant("A working set, one version", "a closed document stays mapped until the collector runs",
           "app/registry.py", "partial(self._recount, weakref.ref(doc))", "partial(self._recount, lambda: doc)",
           ("tests/test_working_set_rules.py",)),
    Mutant("Zoomed out, the picture is the items' own", "masks from the aggregates' boxes alone",
           "spatial/overview.py", "        if finer == band or not len(aggregates):", "        if True:",
           ("tests/test_masks.py",)),
    Mutant("Zoomed out, the picture is the items' own", "items between a pixel and the band left out",
           "spatial/overview.py", "        small = _sizes(item_boxes) < self.threshold(band)",
           "        small = _sizes(item_boxes) < 0", ("tests/test_masks.py",)),
    Mutant("Zoomed out, the picture is the items' own", "staying aggregates kept across any pan",
           "app/answers.py", "old.band == show.band and old.grid != show.grid", "False",
           ("tests/test_masks.py",)),
    Mutant("Zoomed out, the picture is the items' own", "the page draws an aggregate's box, not its mask",
           "static/app.js", "      if (m) {", "      if (false) {",
           ("tests/test_browser.py::test_zoomed_out_an_aggregate_is_drawn_where_its_notes_are_and_nowhere_else",)),
    Mutant("Zoomed out, the picture is the items' own", "runs of folded edits read oldest first: a moved item's home is one it left",
           "spatial/overview.py", "        for run in self._folded:  # items edits added, moved or removed, folded (oldest first)",
           "        for run in reversed(self._folded):",
           ("tests/test_overview.py::test_after_items_move_again_and_again_each_ones_aggregate_at_every_band_is_the_one_holding_it",)),
    Mutant("Zoomed out, the picture is the items' own", "an aggregate's parent read as built, the folded edits' skipped",
           "spatial/overview.py", "                for folded in (run.rows[at] for run in self._folded if at in run.rows):  # oldest first",
           "                for folded in ():",
           ("tests/test_overview.py::test_after_items_move_again_and_again_each_aggregates_parent_at_every_band_above_holds_it",)),
    Mutant("Imports are all or nothing", "a bad line skipped, the rest stored", "app/items.py",
           '                raise ItemError(f"line {number(row)}: {_why(error, line)}") from None', "                continue",
           ("tests/test_promises.py::test_an_import_longer_than_a_batch_whose_last_line_is_bad_stores_nothing",
            "tests/test_service.py::test_a_bad_line_stores_nothing_and_is_named")),
    Mutant("Imports are all or nothing", "line numbers count item lines, not the file's", "app/items.py",
           '        first += data.count(b"\\n", 0, end)', "        first += len(_ITEM_LINE.findall(data, 0, end))",
           ("tests/test_attacks.py::test_blank_lines_are_passed_over_a_block_at_a_time", "tests/test_service.py")),
    Mutant("Imports are all or nothing", "a big file's reader names a line too long before a bad line ahead of it",
           "app/importers/ndjson.py",
           "                    except Exception as error:  # raised once the blocks before it are decoded\n"
           "                        failed = error",
           "                    except Exception as error:\n                        raise error",
           ("tests/test_parallel_decode.py",)),
    Mutant("Imports are all or nothing", "a block's bad line named by its line in the block, not in the file",
           "app/importers/ndjson.py", "raise _numbered(block, lines + 1,",
           "raise _numbered(block, 1,", ("tests/test_parallel_decode.py",)),
    Mutant("Imports are all or nothing", "a big file's batches joined with their items' ends shifted",
           "app/items.py", "    starts = np.cumsum([0] + [p[-1] if len(p) else 0 for p in parts[:-1]])",
           "    starts = [0] + [p[-1] if len(p) else 0 for p in parts[:-1]]",
           ("tests/test_parallel_decode.py",)),
    Mutant("Nothing is shown before the store has it", "an edit shown before it is written", "app/documents.py",
           "            write.write_edits(version, changes, len(edited.tree), bounds)\n        self._publish(edited)",
           "            self._publish(edited)\n            write.write_edits(version, changes, len(edited.tree), bounds)",
           ("tests/test_promises.py::test_a_write_the_store_refuses_is_never_shown",)),
    Mutant("A crash loses nothing committed", "a failed transaction committed", "app/stores/sqlite.py",
           '            if self._db.in_transaction:  # SQLite rolls some failures (a full disk) back itself\n                self._db.execute("ROLLBACK")',
           '            if self._db.in_transaction:\n                self._db.execute("COMMIT")',
           ("tests/test_crash.py", "tests/test_store.py::test_a_write_that_fails_leaves_nothing")),
    Mutant("A crash loses nothing committed", "edits saved by their count only, never by their age",
           "app/main.py", "        registry.save_old_edits(save_edits_seconds)\n", "",
           ("tests/test_crash.py::test_edits_are_saved_soon_after_they_are_made_so_a_kill_leaves_none_to_replay",)),
    Mutant("A crash loses nothing committed", "an edit file newer than the store taken for a stale one, unsaid",
           "app/editfile.py", "    if version > newest:  # the store lost the edits it holds: restored from a backup, or cut short\n",
           "    if False:\n",
           ("tests/test_crash.py::test_an_edit_file_newer_than_the_store_or_following_other_edits_is_removed",)),
    Mutant("A crash loses nothing committed", "an edit file taken without what it follows checked",
           "app/editfile.py", '    unfollowed = _unfollowed(state["follows"], version, store, doc_id)\n',
           "    unfollowed = None\n",
           ("tests/test_crash.py::test_a_store_restored_from_a_backup_never_shows_the_edits_saved_after_it",
            "tests/test_crash.py::test_an_edit_file_newer_than_the_store_or_following_other_edits_is_removed")),
    Mutant("A crash loses nothing committed", "edits a full disk refused taken for saved, never tried again",
           "app/documents.py", "                    self.edits_saved = before\n", "                    pass\n",
           ("tests/test_crash.py::test_edits_a_full_disk_refuses_leave_no_file_and_are_saved_once_there_is_room",)),
    Mutant("A crash loses nothing committed", "the old base's saved count not subtracted after a compaction",
           "app/documents.py", "        since = snap.edits - (saved if base_id == snap.base_id else 0)",
           "        since = snap.edits - saved",
           ("tests/test_crash.py::test_edits_are_saved_beside_a_compactions_new_base_as_beside_the_old",)),
    Mutant("A crash loses nothing committed", "every edit restarts the clock of a save by age", "app/documents.py",
           "        if self._unsaved_since is None:\n            self._unsaved_since = time.monotonic()\n        self.save_edits()",
           "        self._unsaved_since = time.monotonic()\n        self.save_edits()",
           ("tests/test_crash.py::test_a_steady_stream_of_edits_is_saved_by_the_age_of_its_first_not_saved",)),
    Mutant("A crash loses nothing committed", "a document closed past the budget does not save its edits",
           "app/registry.py", "                    doc.save_edits(every=1)  # its next open replays none", "                    pass",
           ("tests/test_crash.py::test_a_document_closed_past_the_budget_saves_its_edits",)),
    Mutant("A crash loses nothing committed", "a save overwrites another worker's newer edit file", "app/documents.py",
           "                if (editfile.saved_version(path) or -1) < snap.version:", "                if True:",
           ("tests/test_crash.py::test_a_save_never_overwrites_another_workers_newer_edit_file",)),
    Mutant("An edit costs the same however large the document",
           "an open from an edit file gives the tree a fresh tree's buffer", "spatial/quadtree.py",
           '            tree.max_buffered = int(edits["max_buffered"][0])',
           "            tree.max_buffered = 256 + tree._n // 512",
           ("tests/test_crash.py::test_an_edit_after_an_open_took_edits_from_their_file_never_rebuilds_the_tree",)),
    Mutant("A crash loses nothing committed", "an import's version bumped in a transaction of its own",
           "app/documents.py",
           "                    write.bump()\n"
           "                    old_rows = write.import_base(staged, version, base_id, len(table), bounds)\n",
           "                    write.bump()\n"
           "                with self.store.writing(self.id) as write:\n"
           "                    old_rows = write.import_base(staged, version, base_id, len(table), bounds)\n",
           ("tests/test_import_kill.py",)),
    Mutant("An import never stops other documents' writers", "a commit copies another's rows into the database",
           "app/stores/sqlite.py", '        db.execute("PRAGMA wal_autocheckpoint = 0")', "        pass",
           ("tests/test_store.py::test_no_commit_copies_the_wal_into_the_database_the_checkpointer_does",)),
    Mutant("A compaction never stops the writers", "a dropped row's freed pages written again (zeroed)",
           "app/stores/sqlite.py", '        db.execute("PRAGMA secure_delete = FAST")', "        pass",
           ("tests/test_store.py::test_dropping_a_rowset_does_not_write_its_pages_again",)),
    Mutant("A crash loses nothing committed", "the WAL never cut back", "app/stores/sqlite.py",
           '        db.execute(f"PRAGMA journal_size_limit = {WAL_LIMIT_BYTES}")', "        pass",
           ("tests/test_store.py::test_no_commit_copies_the_wal_into_the_database_the_checkpointer_does",
            "tests/test_attacks.py::test_a_large_import_leaves_the_write_ahead_log_within_its_limit")),
    Mutant("A crash loses nothing committed", "the WAL never copied beside the writers", "app/stores/sqlite.py",
           '            self._db.execute("PRAGMA wal_checkpoint(PASSIVE)")', "            pass",
           ("tests/test_store.py::test_no_commit_copies_the_wal_into_the_database_the_checkpointer_does",)),
    Mutant("Bad input is a 4xx", "bytes that are not UTF-8 escape as a 500", "app/items.py",
           "_UNREADABLE = (msgspec.DecodeError, UnicodeDecodeError, RecursionError)",
           "_UNREADABLE = (msgspec.DecodeError, RecursionError)",
           ("tests/test_attacks.py::test_bad_bytes_in_an_edit_are_a_422_never_a_500",)),
    Mutant("Every item is addressable", "an id with a slash unreachable", "app/routers/items.py",
           '@router.get("/{item:path}", response_class=JSONBytes', '@router.get("/{item}", response_class=JSONBytes',
           ("tests/test_attacks.py::test_every_id_is_addressable_and_a_path_that_is_not_utf8_is_refused",)),
    Mutant("Readers never see a mix", "an older catch-up shown over a newer write", "app/documents.py",
           "        if snap.version < self.snapshot.version:\n            return\n", "",
           ("tests/test_service.py::test_readers_during_an_import_see_the_old_or_the_new_version_never_a_mix",
            "tests/test_documents.py", "tests/test_working_set_rules.py")),
    Mutant("What goes in comes out", "PATCH replaces the item instead of merging", "app/documents.py",
           "merged = {**msgspec.json.decode(snap.item_json(pos)), **fields, \"id\": item_id}",
           "merged = {**fields, \"id\": item_id}",
           ("tests/test_items_api.py", "tests/test_client.py")),
    Mutant("What goes in comes out", "an upsert moves the item to the end", "app/table.py",
           "        order = np.argsort(place[keep], kind=\"stable\")", "        order = np.arange(int(keep.sum()))",
           ("tests/test_table.py", "tests/test_search.py")),
    Mutant("Search finds what people type", "accents kept", "app/text.py",
           "    if not accents:\n        decomposed", "    if False:\n        decomposed",
           ("tests/test_search.py",)),
    Mutant("Search finds what people type", "whole words not checked", "app/search.py",
           '    if options.whole == "words":', "    if False:",
           ("tests/test_search.py",)),
    Mutant("Search finds what people type", "searches in the thread pool every request shares", "app/routers/search.py",
           "            return await asyncio.get_running_loop().run_in_executor(self.pool, fn, *args)",
           "            from fastapi.concurrency import run_in_threadpool\n\n            return await run_in_threadpool(fn, *args)",
           ("tests/test_search.py",)),
    Mutant("Search finds what people type", "a first page counts every hit, however many", "app/search.py",
           "sum(1 for _ in itertools.islice(hits, TOTAL_CAP + 1 - len(page))) if more else 0",
           "sum(1 for _ in hits) if more else 0",
           ("tests/test_search.py::test_a_first_page_counts_hits_up_to_the_cap_and_no_further",)),
    Mutant("Search finds what people type", "total_exact always true, past the cap too", "app/search.py",
           "        counted <= TOTAL_CAP,\n", "        True,\n",
           ("tests/test_search.py::test_total_is_exact_up_to_the_cap_and_says_at_least_past_it",)),
    Mutant("Search finds what people type", "whole words look at one byte before a hit", "app/search.py",
           "index.text[max(0, start - 4) : start]", "index.text[max(0, start - 1) : start]",
           ("tests/test_search.py::test_whole_words_see_a_letter_beyond_ascii_on_either_side",)),
    Mutant("Search finds what people type", "NFKC removed from the fold", "app/text.py",
           '    text = unicodedata.normalize("NFKC", text)\n', "",
           ("tests/test_search.py::test_matched_accents_still_fold_full_width_forms_and_decomposed_accents",)),
    Mutant("Search finds what people type", "an item edited, then deleted, still found", "app/snapshots.py",
           " for pos, (_, body) in self.overlay.items() if pos not in self.removed}",
           " for pos, (_, body) in self.overlay.items()}",
           ("tests/test_search.py::test_an_item_edited_then_deleted_is_no_longer_found",)),
    Mutant("Search finds what people type", "the scan stops at each block's end", "app/text.py",
           "pattern.finditer(text, at, min(size, block + len(needle) - 1))", "pattern.finditer(text, at, block)",
           ("tests/test_search.py::test_a_phrase_is_found_across_the_scans_blocks",)),
    Mutant("Search finds what people type", "the folded query's limit quadrupled", "app/search.py",
           "MAX_QUERY_BYTES = 1024", "MAX_QUERY_BYTES = 4096",
           ("tests/test_search.py::test_a_query_folding_past_its_limit_is_a_422_that_says_so",)),
    Mutant("A working set, one version", "a hit does not count as a use (FIFO)", "app/registry.py",
           "                self._open.move_to_end(doc_id)", "                pass",
           ("tests/test_working_set.py", "tests/test_working_set_rules.py")),
    Mutant("A working set, one version", "evict() ignores pins", "app/registry.py",
           "                if doc.pins == 0 and not doc._watchers:", "                if not doc._watchers:",
           ("tests/test_working_set.py", "tests/test_working_set_rules.py")),
    Mutant("A working set, one version", "evict() ignores streams' watchers", "app/registry.py",
           "                if doc.pins == 0 and not doc._watchers:", "                if doc.pins == 0:",
           ("tests/test_working_set.py", "tests/test_working_set_rules.py")),
    Mutant("A working set, one version", "the follower ignores deletions", "app/registry.py",
           'change.kind in ("delete", "compact")', 'change.kind in ("compact",)',
           ("tests/test_working_set.py", "tests/test_working_set_rules.py")),
    Mutant("A working set, one version", "no catch-up right after an open", "app/registry.py",
           "                    # What committed while it opened was in the log before the follower could see it\n                    doc.refresh()",
           "                    pass",
           ("tests/test_working_set.py", "tests/test_working_set_rules.py")),
    Mutant("A working set, one version", "an edit applied to the snapshot held, not the one caught up", "app/documents.py",
           "            snap = self._caught_up(self.snapshot, meta, writing=True)\n            if callable(changes):",
           "            snap = self.snapshot\n            if callable(changes):",
           ("tests/test_working_set.py", "tests/test_working_set_rules.py")),
    Mutant("A working set, one version", "an unwritten version waited for", "app/registry.py",
           "            if doc.snapshot.version < version:\n                raise Conflict(",
           "            if doc.snapshot.version < version and time.monotonic() >= deadline:\n                raise Conflict(",
           ("tests/test_working_set_rules.py",)),
    Mutant("A working set, one version", "a document bigger than the budget opened for every request",
           "app/registry.py", "            for doc_id, doc in list(self._open.items())[:-1]:",
           "            for doc_id, doc in list(self._open.items()):",
           ("tests/test_working_set_rules.py",)),
    Mutant("A working set, one version", "a file's items left in the import's order", "app/snapfile.py",
           '        rank = parts.pop("ids")  # a fresh base\'s tree holds each position once: where each went',
           '        rank = parts.pop("ids") * 0 + np.arange(len(table))',
           ("tests/test_snapshot_blocks.py",)),
    Mutant("A working set, one version", "two documents' frames taken for each other in the cache", "app/frames.py",
           "        key = (self._key, f)", "        key = (0, f)",
           ("tests/test_frames.py",)),
    Mutant("A working set, one version", "a bucket's items written over each other, its cursor not moved",
           "app/frames.py", "            cursor += sizes", "            pass",
           ("tests/test_frames.py",)),
    Mutant("A working set, one version", "a snapshot file read with the device's read-ahead at each fault",
           "app/snapfile.py", "            mapped.madvise(mmap.MADV_RANDOM)", "            pass",
           ("tests/test_snapshot_blocks.py",)),
    Mutant("A working set, one version", "the store's rows keep a blob beside their JSON again",
           "app/stores/base.py", 'b"", LEAN', "pack(bodies), ZSTD",
           ("tests/test_store.py", "tests/test_snapshot_blocks.py")),
    Mutant("A working set, one version", "a file stores its tree's ids, its slots", "app/snapfile.py",
           '"tree.shape": shape})',
           '"tree.shape": shape, "tree.ids": np.arange(n)})',
           ("tests/test_snapshot_blocks.py",)),
    Mutant("A working set, one version", "a band's boxes written beside its tree's", "spatial/overview.py",
           '    out[f"{level}.slot"] = band.boxes.slot',
           '    out[f"{level}.slot"], out[f"{level}.boxes"] = band.boxes.slot, band.boxes[:]',
           ("tests/test_snapshot_blocks.py",)),
    Mutant("A working set, one version", "an id looked up in a file's half hashes by its whole hash",
           "app/table.py", "    return high_halves(hashes) if dtype == np.uint32 else hashes", "    return hashes",
           ("tests/test_snapshot_blocks.py",)),
    Mutant("A working set, one version", "ids looked up together through a search left unchecked",
           "app/table.py", "            watch.check(hashes[max(lo - 1, 0) : lo + 1])", "            pass",
           ("tests/test_snapshot_blocks.py",)),
    Mutant("A working set, one version", "an open's saved edits taken without the aggregates they changed",
           "spatial/overview.py", "        clone._folded = (_Folded(rows, items[order], homes[order, 0], homes[order, 1]),)",
           "        clone._folded = (_Folded({}, items[order], homes[order, 0], homes[order, 1]),)",
           ("tests/test_documents.py",)),
    Mutant("An edit costs the same however large the document", "an older run of folded edits read over a newer",
           "spatial/overview.py",
           "            for folded in (run.rows[band] for run in self._folded if band in run.rows):  # oldest first",
           "            for folded in (run.rows[band] for run in reversed(self._folded) if band in run.rows):",
           ("tests/test_overview.py", "tests/test_documents.py")),
    Mutant("A working set, one version", "a damaged edit file taken as it is",
           "app/editfile.py", "    if len(payload) != size or xxhash.xxh3_64_intdigest(payload) != digest:",
           "    if len(payload) != size:", ("tests/test_documents.py",)),
    Mutant("A working set, one version", "an item's home taken to the band after an empty one",
           "spatial/overview.py", 'at = np.searchsorted(self._starts, homes, side="right") - 1',
           'at = np.searchsorted(self._starts, homes, side="left") - 1',
           ("tests/test_overview.py", "tests/test_zoom_out.py")),
    Mutant("A working set, one version", "a file's int32 id ends stored in the rows as they are",
           "app/stores/base.py", "packed.offsets[start : stop + 1].astype(np.int64) - lo",
           "packed.offsets[start : stop + 1] - lo", ("tests/test_store.py",)),
    Mutant("What goes in comes out", "an export of a file laid out in the tree's order follows the tree",
           "app/snapshots.py", '        return positions[np.argsort(places, kind="stable")]',
           "        return np.sort(positions)",
           ("tests/test_snapshot_blocks.py",)),
    Mutant("Search finds what people type", "an edited item of a file laid out in the tree's order moves",
           "app/snapshots.py", "        return base.with_edits(changed, self.removed, self._place)",
           "        return base.with_edits(changed, self.removed)",
           ("tests/test_snapshot_blocks.py",)),
    Mutant("Readers never see a mix", "a tree's removals seen by its copies made before them",
           "spatial/quadtree.py", "        dead.at[index] = self._horizon", "        dead.at[index] = _NEVER",
           ("tests/test_quadtree_edits.py",)),
    Mutant("Readers never see a mix", "a tree and its copy, both edited, share their tombstones",
           "spatial/quadtree.py",
           "        if dead is None or self._clock != dead.tip or dead.tip == _LAST_TICK:",
           "        if dead is None or dead.tip == _LAST_TICK:",
           ("tests/test_quadtree_edits.py",)),
    Mutant("An edit costs the same however large the document", "a tree's copy copies its tombstones",
           "spatial/quadtree.py", "        clone.__dict__.update(self.__dict__)\n",
           "        clone.__dict__.update(self.__dict__)\n        if self._dead is not None:\n"
           "            clone._dead = _Tombstones(self._dead.at.copy())\n"
           "            clone._dead.tip = self._dead.tip\n",
           ("tests/test_quadtree_edits.py",)),
    Mutant("An edit costs the same however large the document", "a tree's copy copies its insert buffer",
           "spatial/quadtree.py", "        clone.__dict__.update(self.__dict__)\n",
           "        clone.__dict__.update(self.__dict__)\n        clone._own_inserts(len(self._inserts.ids))\n"
           "        clone._pack()\n",
           ("tests/test_quadtree_edits.py::test_a_copy_of_a_tree_with_buffered_inserts_costs_nothing_per_insert",
            "tests/test_documents.py::test_an_edit_costs_the_same_however_many_edits_are_pending")),
    Mutant("Readers never see a mix", "a buffered row removed since is still found", "spatial/_kernels.py",
           "        if gone[j] >= horizon:  # removed (or moved) since\n            continue\n", "",
           ("tests/test_quadtree_edits.py",)),
    Mutant("An edit costs the same however large the document",
           "a document's tree rebuilt by an edit before its compaction", "app/snapshots.py",
           "        tree.max_buffered = 2 * _compact_after(len(table))\n", "",
           ("tests/test_documents.py",)),
    Mutant("An edit costs the same however large the document",
           "an edit checks each band it changes whole", "spatial/overview.py",
           "        built = bands.row(band, index) if isinstance(bands, _CheckedBands) else bands.get(band)\n",
           "        built = bands.get(band)\n",
           ("tests/test_snapshot_blocks.py",)),
    Mutant("An edit costs the same however large the document", "an edit copies the items edited since the base",
           "app/snapshots.py", "added, overlay, removed = self.added.mutate(), self.overlay.mutate()",
           "added, overlay, removed = Map(dict(self.added)).mutate(), Map(dict(self.overlay)).mutate()",
           ("tests/test_documents.py::test_an_edit_costs_the_same_however_many_edits_are_pending",)),
    Mutant("An edit costs the same however large the document", "an overview's copy copies its members",
           "spatial/overview.py", "        clone._owned = set()\n",
           "        clone._owned = set()\n        clone._member = Map(dict(self._member))\n",
           ("tests/test_documents.py::test_an_edit_costs_the_same_however_many_edits_are_pending",)),
    Mutant("A compaction never stops the writers", "a compaction builds in the writers' turn",
           "app/documents.py",
           "            _, staged = self._built_and_staged(table, snap.version, base_id, step, in_memory=False)\n",
           "            with self._edit_lock:\n"
           "                _, staged = self._built_and_staged(table, snap.version, base_id, step, in_memory=False)\n",
           ("tests/test_documents.py::TestDocument",)),
    Mutant("A compaction never stops the writers", "a compaction whose file is refused builds it in memory",
           "app/documents.py",
           "            _, staged = self._built_and_staged(table, snap.version, base_id, step, in_memory=False)\n",
           "            _, staged = self._built_and_staged(table, snap.version, base_id, step, in_memory=True)\n",
           ("tests/test_documents.py::test_a_compaction_whose_file_cannot_be_written_stops_and_holds_no_index_in_memory",)),
    Mutant("A compaction never stops the writers", "a compaction drops the edits made during its build",
           "app/stores/base.py",
           '"DELETE FROM edits WHERE doc_id = ? AND version <= ?", self._id, version)',
           '"DELETE FROM edits WHERE doc_id = ?", self._id)',
           ("tests/test_documents.py::TestDocument",)),
    Mutant("A compaction never stops the writers", "a compaction's rows written in one transaction",
           "app/stores/base.py",
           "            for row in chunks(table):\n"
           "                values = (doc_id, staged.rowset, *encoded(row, pack))\n"
           "                with self._unlocked(doc_id) as write:\n"
           "                    write._write_base_rows(iter([values]))\n"
           "                staged.rows += 1\n",
           "            with self._unlocked(doc_id) as write:\n"
           "                for row in chunks(table):\n"
           "                    values = (doc_id, staged.rowset, *encoded(row, pack))\n"
           "                    write._write_base_rows(iter([values]))\n"
           "                    staged.rows += 1\n",
           ("tests/test_store.py::test_a_compactions_rows_are_staged_unseen_while_writers_go_on_then_swapped_in_one_write",)),
    Mutant("A compaction never stops the writers", "staged rows read before the document names them",
           "app/stores/base.py", " JOIN documents d ON d.id = b.doc_id AND d.rowset = b.rowset WHERE", " WHERE",
           ("tests/test_store.py",)),
    Mutant("A compaction never stops the writers", "a base's own rows dropped as a replaced one's",
           "app/stores/base.py", "AND rowset != (SELECT rowset FROM documents WHERE id = ?)", "AND ? IS NOT NULL",
           ("tests/test_store.py",)),
    Mutant("An import never stops other documents' writers", "an import built inside the store's write",
           "app/documents.py", "        done = self._import_beside(imported, max_items, replace)\n", "        done = None\n",
           ("tests/test_documents.py::test_an_import_is_built_outside_the_stores_write_and_built_again_if_another_process_wrote",)),
    Mutant("An import never stops other documents' writers", "an import stored over another process's edit",
           "app/documents.py", 'if meta["version"] != version - 1:', "if False:",
           ("tests/test_documents.py::test_an_import_is_built_outside_the_stores_write_and_built_again_if_another_process_wrote",)),
    Mutant("A compaction never stops the writers", "a compaction stored over an import made meanwhile",
           "app/documents.py", 'if meta["base_id"] != snap.base_id:', "if False:",
           ("tests/test_documents.py::TestDocument",)),
    Mutant("A compaction never stops the writers", "followers ignore another process's compaction",
           "app/registry.py", 'change.kind in ("delete", "compact")', 'change.kind in ("delete",)',
           ("tests/test_working_set_rules.py",)),
    Mutant("A working set, one version", "a first answer checks the frames' whole index", "app/frames.py",
           "            watch.check(*(self.first[a:b] for a, b in ends), *(self.at[a:b] for a, b in ends))\n",
           "            watch.check(self.first, self.at)\n",
           ("tests/test_snapshot_blocks.py",)),
    Mutant("Every worker takes its share", "one socket shared by the workers", "app/workers.py",
           "    balanced = reuse_port_available()", "    balanced = False",
           ("tests/test_workers.py",)),
    Mutant("Every worker takes its share", "the kill alarm removed: a worker that hangs holds the server up",
           "app/workers.py", "        signal.alarm(int(STOP_SECONDS))\n", "",
           ("tests/test_workers.py::test_a_worker_that_hangs_on_sigterm_is_killed_after_the_grace_period",)),
    Mutant("Installed from its wheel", "the page left out of the wheel", "pyproject.toml",
           'app = ["static/*"]', 'app = []', ("tests/test_wheel.py",)),
    Mutant("No request waits for a compile", "warm-up leaves mapped snapshots out", "app/housekeeping.py",
           "        _answer(mapped)\n", "",
           ("tests/test_warm_up.py",)),
    Mutant("Traced when asked", "telemetry off whatever is asked", "app/main.py",
           "telemetry=None if settings.telemetry else", "telemetry=", ("tests/test_telemetry.py",)),
    Mutant("One socket write a response", "writes go straight to the transport", "app/protocol.py",
           "super().connection_made(cast(asyncio.Transport, _Cork(transport, asyncio.get_running_loop())))",
           "super().connection_made(transport)", ("tests/test_protocol.py",)),
    Mutant("One socket write a response", "close() does not flush", "app/protocol.py",
           "    def close(self) -> None:\n        self.flush()\n        self.raw.close()",
           "    def close(self) -> None:\n        self.raw.close()", ("tests/test_protocol.py",)),
    Mutant("One socket write a response", "a held write waits 0.2 s, not one loop turn", "app/protocol.py",
           "            self._flush_soon = self._loop.call_soon(self.flush)",
           "            self._flush_soon = self._loop.call_later(0.2, self.flush)", ("tests/test_protocol.py",)),
    Mutant("Both stores keep the same promises", "PostgreSQL writes without a transaction", "app/stores/postgres.py",
           "        with self._unless_unreachable(), self._pool.connection() as db, db.transaction():",
           "        with self._unless_unreachable(), self._pool.connection() as db:",
           ("tests/test_store.py",)),
    Mutant("Replicas agree", "no safety poll: a missed NOTIFY is missed for good", "app/stores/postgres.py",
           "        if self._woken.is_set() or now - self._polled >= POLL_SECONDS:",
           "        if self._woken.is_set():", ("tests/test_store.py", "tests/test_replicas.py")),
    Mutant("No zoom level is blank", "an item joining an aggregate leaves its z", "spatial/overview.py",
           "(box, count + 1, total + area, max(top, int(z)), kind, parent)", "(box, count + 1, total + area, top, kind, parent)",
           ("tests/test_overview.py", "tests/test_zoom_out.py")),
    Mutant("No zoom level is blank", "a removal leaves its area in cover", "spatial/overview.py",
           "(b, count - 1, max(0.0, total - area), z, kind, parent)", "(b, count - 1, total, z, kind, parent)",
           ("tests/test_overview.py", "tests/test_zoom_out.py")),
    Mutant("No zoom level is blank", "from_band ignored", "app/routers/viewport.py",
           "    if from_band is None:\n        old_shown", "    if True:\n        old_shown",
           ("tests/test_zoom_out.py",)),
    Mutant("Under load", "an off-by-one drops a viewport's last item", "app/answers.py",
           "        found = snap.tree.query(show.rect, min_size=show.size)",
           "        found = snap.tree.query(show.rect, min_size=show.size)[:-1]",
           ("tests/test_load.py", "-m", "load")),
    Mutant("Imports are all or nothing", "the store's rows, staged beside a build that fails, kept",
           "app/documents.py", "                    self._drop_rows(staging.result().rowset)\n",
           "                    staging.result()\n",
           ("tests/test_documents.py::test_an_import_whose_index_or_rows_fail_while_both_are_written_stores_nothing",)),
    Mutant("Imports are all or nothing", "the store's rows, written beside a build inside one write, failing unnoticed",
           "app/documents.py", "                    storing.result()\n", "",
           ("tests/test_documents.py::test_an_import_built_again_inside_a_write_whose_rows_fail_stores_nothing",)),
    Mutant("No zoom level is blank", "a band's cells ordered by a key that forgets the first column",
           "spatial/_kernels.py", "out[i] = np.uint64(cx - x0) * kx", "out[i] = np.uint64(cx) * kx",
           ("tests/test_overview.py",)),
    Mutant("No zoom level is blank", "an item whose area overflows weighs infinitely in its aggregate",
           "spatial/_kernels.py", "        out[i] = area if np.isfinite(area) else 0.0\n", "        out[i] = area\n",
           ("tests/test_overview.py", "tests/test_zoom_out.py")),
    Mutant("An import of any size, in parts", "the band below's boxes held through a band's merge and its tree's build",
           "spatial/overview.py", "            previous = None  # in the elements now\n", "",
           ("tests/test_overview.py",)),
    Mutant("An import of any size, in parts", "the overview's arrays held while the tree is built",
           "app/snapfile.py", "        del array  # let go once written", "        pass",
           ("tests/test_snapshot_blocks.py",)),
    Mutant("No zoom level is blank", "a band's parents written before the band above is merged",
           "spatial/overview.py", 'below = (f"{level}.parent", arrays.pop(f"{level}.parent"))', "below = None",
           ("tests/test_overview.py",)),
    Mutant("An import of any size, in parts", "an import's ids, offsets and id index held in memory",
           "app/documents.py", "    return ItemTable.merge([table], spill=spill).spilled(spill)",
           "    return ItemTable.merge([table], spill=spill)",
           ("tests/test_table.py",)),
    Mutant("An import of any size, in parts", "the decoded batches' heap kept through the merge",
           "app/documents.py", "    return_freed_memory()  # the decoded batches' heap\n", "",
           ("tests/test_import_memory.py::test_an_import_hands_its_decoded_batches_heap_back_before_the_merge",)),
    Mutant("Nothing is shown before the store has it", "a full disk outside the store answered 500", "app/errors.py",
           "        if error.errno not in FULL_DISK:\n            raise\n", "        raise\n",
           ("tests/test_full_disk.py",)),
    Mutant("Nothing is shown before the store has it", "a full disk at an import's build taken for a read-only one",
           "app/documents.py", "base_id, True):  # True: a full disk raised", "base_id):",
           ("tests/test_full_disk.py::test_a_full_disk_while_a_new_base_is_built_refuses_the_import_and_the_compaction",)),
    Mutant("Nothing is read before it is allowed", "an NDJSON line measured only once the body is spooled",
           "app/routers/documents.py", "                    lines.arrived(chunk)\n", "                    pass\n",
           ("tests/test_attacks.py::test_a_long_line_over_http_is_refused_as_it_arrives_not_once_the_body_is_spooled",)),
    Mutant("Nothing is read before it is allowed", "an import's body spooled in the system's temp",
           "app/routers/documents.py", "max_size=SPOOL_IN_MEMORY, dir=str(directory))", "max_size=SPOOL_IN_MEMORY)",
           ("tests/test_full_disk.py::test_an_imports_body_is_spooled_in_the_data_directory_and_a_full_disk_there_is_a_507",)),
    Mutant("Nothing is shown before the store has it", "an upload's part on a full disk answered 500", "app/uploads.py",
           "    @refused_when_full(\"keeping the upload's part\")\n    def write(", "    def write(",
           ("tests/test_full_disk.py::test_an_upload_part_on_a_full_disk_is_a_507_that_keeps_the_upload",)),
]  # fmt: skip


def scratch_copy(into: Path) -> None:
    """The checkout's tracked files as they are now (uncommitted changes too), links kept."""
    files = subprocess.run(["git", "ls-files", "-z"], cwd=ROOT, capture_output=True, check=True).stdout
    for name in files.decode().split("\0"):
        if not name:
            continue
        source, target = ROOT / name, into / name
        target.parent.mkdir(parents=True, exist_ok=True)
        if source.is_symlink():
            target.symlink_to(os.readlink(source))
        elif source.exists():
            shutil.copy2(source, target)


def run(mutant: Mutant, copy: Path, env: dict[str, str]) -> tuple[str, float]:
    """``(outcome, seconds)``: caught (the tests failed), missed (they passed), or broken (the
    mutant's text is not in the file)."""
    path = copy / mutant.path
    original, stamp = path.read_text(), path.stat()
    if original.count(mutant.old) != 1:
        return f"broken: the text occurs {original.count(mutant.old)} times", 0.0
    path.write_text(original.replace(mutant.old, mutant.new))
    started = time.monotonic()
    try:
        done = subprocess.run(
            [sys.executable, "-m", "pytest", "-x", "-q", "-p", "no:cacheprovider", *mutant.tests],
            cwd=copy,
            env=env,
            capture_output=True,
            text=True,
            timeout=TIMEOUT,
        )
        outcome = "missed" if done.returncode == 0 else "caught"
        if done.returncode not in (0, 1):  # 2+: an error collecting or running, not a failing test
            outcome = f"caught (pytest exit {done.returncode})"
    except subprocess.TimeoutExpired:
        outcome = f"caught (hung past {TIMEOUT} s)"
    finally:
        path.write_text(original)
        os.utime(path, ns=(stamp.st_atime_ns, stamp.st_mtime_ns))  # its time too: the cache stays good
    return outcome, time.monotonic() - started


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(
        prog="python -m benchmarks.promises", description=__doc__.split("\n\n")[0]
    )
    parser.add_argument(
        "--only",
        help="only the mutants whose promise or description holds one of these (comma-separated) words",
    )
    parser.add_argument("--list", action="store_true", help="list the mutants and exit")
    args = parser.parse_args(argv)
    words = [w.strip().lower() for w in (args.only or "").split(",") if w.strip()]
    mutants = [m for m in MUTANTS if not words or any(w in f"{m.promise} {m.what}".lower() for w in words)]
    if args.list:
        for m in mutants:
            print(f"{m.promise}: {m.what} ({m.path}; {' '.join(m.tests)})")
        return
    work = Path(tempfile.mkdtemp(prefix="vantage-promises-"))
    copy = work / "checkout"
    scratch_copy(copy)
    env = {**os.environ, "NUMBA_CACHE_DIR": str(work / "numba-cache"), "PYTHONPATH": str(copy)}
    print(f"scratch copy in {copy}; {len(mutants)} mutants", file=sys.stderr, flush=True)
    rows = []
    for k, mutant in enumerate(mutants, 1):
        outcome, seconds = run(mutant, copy, env)
        rows.append((mutant, outcome, seconds))
        print(
            f"[{k}/{len(mutants)}] {mutant.promise}: {mutant.what}: {outcome} ({seconds:.0f} s)",
            file=sys.stderr,
            flush=True,
        )
    print("| promise | mutant | outcome | seconds |")
    print("|---|---|---|---:|")
    for mutant, outcome, seconds in rows:
        print(f"| {mutant.promise} | {mutant.what} | {outcome} | {seconds:.0f} |")
    missed = [m for m, outcome, _ in rows if not outcome.startswith("caught")]
    print(f"\n{len(rows) - len(missed)} of {len(rows)} caught")
    sys.exit(1 if missed else 0)


if __name__ == "__main__":
    main()
