"""Who may write, and read when so configured: bearer tokens from the settings, compared in
constant time.

Whether a token is needed is decided once, from the settings: ``VANTAGE_TOKENS`` or
``VANTAGE_TOKENS_FILE`` set means yes. The file is re-read when it changes (one ``stat`` a
request); an empty file then means no token from it is valid, a missing or unreadable one that
nothing is accepted until it is back, never that writes are open.
"""

import hmac
import os
import threading
from pathlib import Path

from starlette.exceptions import HTTPException

from .config import Settings

__all__ = ["Tokens"]

CHALLENGE = {"WWW-Authenticate": "Bearer"}


class Tokens:
    """The tokens a request may carry: ``VANTAGE_TOKENS`` plus the lines of ``VANTAGE_TOKENS_FILE``
    (blank lines and lines starting with ``#`` are not tokens)."""

    def __init__(self, settings: Settings) -> None:
        self.required = settings.tokens_required
        self._fixed = [t.strip().encode() for t in settings.tokens.split(",") if t.strip()]
        self._file: Path | None = settings.tokens_file
        self._seen: tuple[tuple[int, int, int], list[bytes]] | None = None  # (file stamp, its tokens)
        self._lock = threading.Lock()

    def check(self, given: str) -> None:
        """Pass if ``given`` is an accepted token (or none is required).

        :raises HTTPException: 401 without a token, 403 with a wrong one, 503 if the tokens
            file is missing or unreadable
        """
        if not self.required:
            return
        accepted = self._fixed + self._from_file()
        if not given:
            raise HTTPException(401, "this needs a token: send `Authorization: Bearer <token>`", CHALLENGE)
        candidate = given.strip().encode()
        # Compare with every token, always: the time taken says nothing about which one nearly matched.
        if not sum(hmac.compare_digest(candidate, token) for token in accepted):
            raise HTTPException(403, "the token is not one this server accepts", CHALLENGE)

    def _from_file(self) -> list[bytes]:
        if self._file is None:
            return []
        try:
            info = os.stat(self._file)
            stamp = (info.st_mtime_ns, info.st_size, info.st_ino)
            seen = self._seen
            if seen is None or seen[0] != stamp:
                with self._lock:
                    lines = self._file.read_bytes().splitlines()
                    tokens = [t.strip() for t in lines if t.strip() and not t.lstrip().startswith(b"#")]
                    self._seen = seen = (stamp, tokens)  # one assignment: readers see old or new, whole
            return seen[1]
        except OSError as error:
            message = f"the tokens file {self._file} cannot be read ({error.strerror}): no token is accepted until it is back"
            raise HTTPException(503, message + " (VANTAGE_TOKENS_FILE)") from None
