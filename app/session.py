"""One stream client's state: the view it was last answered, the newest viewport it sent and
not yet answered (a newer one replaces it: no backlog), its rate, and the streams open."""

from __future__ import annotations

import asyncio
import time
from typing import Literal, NamedTuple

from pydantic import BaseModel, ConfigDict, Field, ValidationError

from .answers import Held, Shown, View, change
from .config import Settings
from .documents import Document
from .snapshots import Snapshot

__all__ = ["Job", "Session", "Streams", "TokenMessage", "ViewMessage"]

LIGHT_SECONDS = 0.0005  # an answer this quick is computed on the event loop (see Session.light)


class ViewMessage(BaseModel):
    """What a client sends: the viewport it pans to, and its level of detail and limit."""

    model_config = ConfigDict(extra="forbid")

    seq: int = Field(0, ge=-(2**63), lt=2**63)
    viewport: tuple[float, float, float, float]
    scale: float | None = Field(None, gt=0)
    min_px: float = Field(0.0, ge=0)
    limit: int | None = Field(None, ge=1)


class TokenMessage(BaseModel):
    """What a client sends to replace its stream's token before it expires."""

    model_config = ConfigDict(extra="forbid")

    token: str = Field(max_length=16384)


class Job(NamedTuple):
    """An answer to compute: for a viewport the client sent, or again for an edit."""

    kind: Literal["view", "edit"]
    seq: int  # the viewport message it answers
    view: View
    cap: int


class Streams:
    """How many streams are open, against the most there may be, and the bytes of answers
    being sent that their clients have not taken yet, against a budget shared by all."""

    def __init__(self, limit: int, unread_budget: int = 256 << 20) -> None:
        self.limit, self.open = limit, 0
        self.unread, self.unread_budget = 0, unread_budget
        self._freed = asyncio.Event()

    async def reserve(self, size: int, timeout: float) -> bool:
        """Count ``size`` bytes about to be sent, once the budget has room for them (an answer
        always has room when nothing else is unread); False if it had none within ``timeout``
        seconds. Clients that never read thus hold the budget, not a copy of an answer each."""
        loop = asyncio.get_running_loop()
        deadline = loop.time() + timeout
        while self.unread and self.unread + size > self.unread_budget:
            self._freed.clear()
            try:
                await asyncio.wait_for(self._freed.wait(), deadline - loop.time())
            except TimeoutError:
                return False
        self.unread += size
        return True

    def release(self, size: int) -> None:
        """The ``size`` bytes of a reserved answer left for its client (or never will)."""
        self.unread -= size
        self._freed.set()  # every waiter looks again


class Session:
    """One client's view: what it was last sent, so the next answer is only the change."""

    def __init__(self, document: Document, settings: Settings) -> None:
        self.document, self.settings = document, settings
        self.answered: Job | None = None  # the last job answered
        self.shown: Shown | None = None  # what it showed
        self.snapshot: Snapshot | None = None  # the version it was answered at
        self.complete = False  # False until an answer fits its cap: the next one starts over
        self.latest: Job | None = None  # the newest viewport not yet answered
        self.renewal: str | None = None  # a token the client sent to replace the stream's
        self.errors: list[str] = []
        self.wake = asyncio.Event()
        self.received = self.sent = 0  # messages, for the log line at the end
        self.allowance, self.checked = settings.max_stream_rate, time.monotonic()  # a token bucket
        self.warned = -1.0  # when the client was last told it is over the rate
        self.cost = 0.0  # seconds the last answer took

    def offer(self, text: str | bytes) -> None:
        """Take a client message: the newest viewport replaces any still waiting."""
        self.received += 1
        if not self._within_rate():
            return
        try:
            message = ViewMessage.model_validate_json(text)
            view = View.of(message.viewport, "viewport", message.scale, message.min_px)
        except ValidationError as error:
            if (renewal := _token_of(text)) is not None:
                self.renewal = renewal
                self.wake.set()
                return
            self.errors.append(
                "; ".join(f"{'.'.join(map(str, e['loc'])) or 'message'}: {e['msg']}" for e in error.errors())
            )
        except ValueError as error:
            self.errors.append(str(error))
        else:
            self.latest = Job("view", message.seq, view, self.settings.cap(message.limit))
        self.wake.set()

    def _within_rate(self) -> bool:
        """Up to ``max_stream_rate`` messages a second (bursts of one second's worth); beyond,
        messages are dropped with an error, one a second at most."""
        now, rate = time.monotonic(), self.settings.max_stream_rate
        self.allowance = min(rate, self.allowance + (now - self.checked) * rate)
        self.checked = now
        if self.allowance >= 1:
            self.allowance -= 1
            return True
        if now - self.warned >= 1:
            self.warned = now
            self.errors.append(
                f"429: over {rate:g} messages a second (VANTAGE_MAX_STREAM_RATE); "
                "messages beyond it are dropped"
            )
            self.wake.set()
        return False

    def take(self) -> Job | None:
        """What to answer next (on the event loop, where ``offer`` runs): the latest viewport,
        else the last one again if the document changed under it."""
        if self.latest is not None:
            job, self.latest = self.latest, None
            return job
        if self.answered is not None and self.document.snapshot is not self.snapshot:
            return self.answered._replace(kind="edit")
        return None

    def light(self, job: Job) -> bool:
        """Whether answering ``job`` is a pan step's small change, cheaper on the event loop
        than a hop to a worker thread and back (which cost more than the answer itself): the
        last answer was complete and quick, and the view kept its level of detail, its base
        and at least half of itself. Anything else may take milliseconds: a thread's work."""
        old, snap = self.answered, self.snapshot
        if old is None or snap is None or not self.complete or self.cost > LIGHT_SECONDS:
            return False
        if snap.base_id != self.document.snapshot.base_id or old.view.min_size != job.view.min_size:
            return False
        a, b = old.view.rect, job.view.rect
        w, h = min(a[2], b[2]) - max(a[0], b[0]), min(a[3], b[3]) - max(a[1], b[1])
        return w >= 0 and h >= 0 and w * h >= 0.5 * (b[2] - b[0]) * (b[3] - b[1])

    def answer(self, job: Job) -> str | None:
        """The message for ``take``'s job; None for an edit that did not touch this view."""
        started = time.perf_counter()
        try:
            return self._answer(job)
        finally:
            self.cost = time.perf_counter() - started

    def _answer(self, job: Job) -> str | None:
        snap = self.document.snapshot
        held = None
        if self.complete and self.shown is not None and self.snapshot is not None:
            held = Held(self.shown, self.snapshot.version, self.snapshot)
        answer = change(snap, job.view, held, job.cap, self.settings.lod_budget, self.document.tiles)
        self.answered, self.snapshot, self.complete = job, snap, not answer.truncated
        self.shown = answer.shown
        return (
            None if answer.empty and job.kind == "edit" else answer.json(type=job.kind, seq=job.seq).decode()
        )


def _token_of(text: str | bytes) -> str | None:
    """The token of a token message; None for anything else."""
    try:
        return TokenMessage.model_validate_json(text).token
    except ValidationError:
        return None
