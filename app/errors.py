"""The service's domain errors, each with the status code it answers; ``main`` maps them once.

Code raises these with a message that says what was wrong and where; the client gets it as
``{"detail": message}``. Anything else that escapes a route (a stray ``KeyError`` included) is
a bug and answers 500.
"""

import errno
from collections.abc import Iterator
from contextlib import contextmanager

from starlette.exceptions import HTTPException

__all__ = [
    "BadRequest",
    "Behind",
    "Busy",
    "Conflict",
    "FULL_DISK",
    "Forbidden",
    "Invalid",
    "NotFound",
    "ServiceError",
    "SlowBody",
    "StorageFull",
    "TooMany",
    "Unauthorized",
    "Unavailable",
    "UnsupportedMedia",
    "refused_when_full",
]

FULL_DISK = frozenset({errno.ENOSPC, errno.EDQUOT})  # a disk, or the user's quota on it, that is full


class ServiceError(HTTPException):
    """An error the client caused or must wait out; ``status`` is its HTTP code, and
    ``retry_after`` (seconds), when set, says when to try again.

    A Starlette ``HTTPException``, so one raised while FastAPI reads a body (the guard's caps)
    reaches the same handler as one raised in a route, not FastAPI's "error parsing the body"."""

    status = 500
    retry_after: int | None = None

    def __init__(self, message: str | None = None) -> None:
        super().__init__(self.status, message or self.__class__.__name__, self._headers() or None)

    @property
    def message(self) -> str:
        return str(self.detail)

    def __str__(self) -> str:  # the message, as an exception's text is (not HTTPException's "422: ...")
        return self.message

    def _headers(self) -> dict[str, str]:
        """Headers the answer carries besides its JSON."""
        return {"Retry-After": str(self.retry_after)} if self.retry_after is not None else {}


class BadRequest(ServiceError):
    """A request no route could take: a Host this server does not answer to, a path that is
    not UTF-8."""

    status = 400


class Unauthorized(ServiceError):
    """No token where one is needed, or a signed one that is expired, forged or malformed."""

    status = 401

    def _headers(self) -> dict[str, str]:
        return {"WWW-Authenticate": "Bearer"}


class Forbidden(ServiceError):
    """A token that does not allow this: not one the server accepts, or one without the grant;
    or a browser origin that may not write."""

    status = 403


class SlowBody(ServiceError):
    """The body did not arrive within the time allowed."""

    status = 408


class NotFound(ServiceError):
    """No such document or item."""

    status = 404


class Conflict(ServiceError):
    """The request contradicts the document's state (a version from the future, say)."""

    status = 409


class TooMany(ServiceError, ValueError):
    """More than a limit allows: items in a document, documents in the store."""

    status = 413


class UnsupportedMedia(ServiceError):
    """A body of a type the route does not take."""

    status = 415


class Invalid(ServiceError, ValueError):
    """Input the client sent is invalid (an item, a viewport); the message says where and why."""

    status = 422


class StorageFull(ServiceError):
    """The store could not take a write (its disk, or its size limit, is full); nothing was written."""

    status = 507


@contextmanager
def refused_when_full(what: str) -> Iterator[None]:
    """A full disk (or quota) met inside, anywhere (a spill, a snapshot file, a spooled body),
    refused as the store's own full disk is: ``StorageFull`` saying what was being written.
    The code inside leaves nothing behind itself (files with no name, temporary names
    removed); this only says why. Also a decorator.

    :raises StorageFull: for ``ENOSPC`` or ``EDQUOT``; any other ``OSError`` as it was
    """
    try:
        yield
    except OSError as error:
        if error.errno not in FULL_DISK:
            raise
        raise StorageFull(
            f"the data directory's disk is full ({error.strerror}) {what}: nothing was stored; free some space"
        ) from error


class Unavailable(ServiceError):
    """Something the request needs cannot be reached now (the tokens file, say)."""

    status = 503


class Behind(ServiceError):
    """This server has not yet caught up with a version the client has seen (``min_version``);
    another try, here or at another replica, will find it."""

    status = 503
    retry_after = 1


class Busy(ServiceError):
    """As many searches as the server runs and queues are under way."""

    status = 503
    retry_after = 1
