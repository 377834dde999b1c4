"""Folding a document's edits into a new base in the background, after the write's answer:
opening the document then maps one file instead of replaying the edits."""

import asyncio

from fastapi.concurrency import run_in_threadpool

from .documents import Document

__all__ = ["Compactions"]


class Compactions:
    """A worker's compactions under way, one a document at most; the app's lifespan waits for
    them as it ends (``finished``)."""

    def __init__(self) -> None:
        self.tasks: set[asyncio.Task[None]] = set()
        self.documents: set[str] = set()  # those being compacted

    def later(self, doc: Document) -> None:
        """Once enough edits piled up in ``doc``, fold them into a new base, in a thread of its
        own: writers wait for it only while it stores the new base (``Document.compact``), not
        while it builds. Call it on the event loop, after a write."""
        if not doc.needs_compaction() or doc.id in self.documents:
            return

        def compact_if_still_needed() -> None:
            if doc.needs_compaction():  # another may have folded the edits since
                doc.compact()

        async def compact() -> None:
            try:
                await run_in_threadpool(compact_if_still_needed)
            finally:
                self.documents.discard(doc.id)

        self.documents.add(doc.id)
        task = asyncio.get_running_loop().create_task(compact())
        self.tasks.add(task)
        task.add_done_callback(self.tasks.discard)

    async def finished(self) -> None:
        """Once the compactions under way are done (none starts meanwhile: no request comes)."""
        for task in list(self.tasks):
            await task
