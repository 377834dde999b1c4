"""The service's domain errors, each with the status code it answers; ``main`` maps them once.

Code raises these with a message that says what was wrong and where; the client gets it as
``{"detail": message}``. Anything else that escapes a route (a stray ``KeyError`` included) is
a bug and answers 500.
"""

__all__ = [
    "Behind",
    "Conflict",
    "Invalid",
    "NotFound",
    "ServiceError",
    "StorageFull",
    "TooMany",
    "UnsupportedMedia",
]


class ServiceError(Exception):
    """An error the client caused or must wait out; ``status`` is its HTTP code, and
    ``retry_after`` (seconds), when set, says when to try again."""

    status = 500
    retry_after: int | None = None

    @property
    def message(self) -> str:
        return str(self.args[0]) if self.args else self.__class__.__name__


class NotFound(ServiceError, LookupError):
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


class Behind(ServiceError):
    """This server has not yet caught up with a version the client has seen (``min_version``);
    another try, here or at another replica, will find it."""

    status = 503
    retry_after = 1
