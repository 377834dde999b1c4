"""Who may do what: static bearer tokens (full access, for the app's own backend) and signed
access tokens (JWT, per document, for the app's users), each checked into a :class:`Grant`.

Whether a token is needed is decided once, from the settings: ``VANTAGE_TOKENS``,
``VANTAGE_TOKENS_FILE`` or a JWT key set means yes. The tokens file is re-read when it changes
(one ``stat`` a request); an empty file then means no token from it is valid, a missing or
unreadable one that nothing is accepted until it is back, never that writes are open.

A signed token is verified with ``VANTAGE_JWT_SECRET`` (HS256; a comma-separated list accepts
each, for a rotation) or ``VANTAGE_JWT_PUBLIC_KEY`` (a PEM file: EdDSA, ES256 or RS256). The
algorithm is pinned to the key's kind, so ``alg: none`` and a public key taken for an HMAC
secret are refused; ``exp`` is required, and ``aud`` checked when ``VANTAGE_JWT_AUDIENCE`` is
set. Its claims: ``docs``, an object mapping a document id (or ``"*"``) to ``"read"`` or
``"write"`` (write includes read); ``create: true`` may create documents; ``sub`` names who,
in the log.
"""

from __future__ import annotations

import functools
import hmac
import math
import os
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import jwt
from cryptography.hazmat.primitives.asymmetric import ec, ed25519, rsa
from cryptography.hazmat.primitives.serialization import load_pem_public_key

from .config import Settings
from .errors import Forbidden, Unauthorized, Unavailable

__all__ = ["Access", "BadKey", "FULL", "Grant", "mint"]

MIN_SECRET_BYTES = 32  # HS256's key: as long as its hash (RFC 7518 section 3.2)
RIGHTS = ("read", "write")


@dataclass(frozen=True, slots=True)
class Grant:
    """What a request's token allows. ``docs`` None: every document, to write (a static token)."""

    docs: dict[str, str] | None
    create: bool = False
    subject: str | None = None
    expires: float | None = None  # seconds since the epoch

    def reads(self, doc: str) -> bool:
        return self.docs is None or doc in self.docs or "*" in self.docs

    def writes(self, doc: str) -> bool:
        return self.docs is None or "write" in (self.docs.get(doc), self.docs.get("*"))

    @property
    def expired(self) -> bool:
        return self.expires is not None and time.time() >= self.expires


FULL = Grant(None, create=True)  # a static token, or no token needed


class BadKey(ValueError):
    """The JWT key settings cannot be used; the message says which and why."""


class Access:
    """The tokens a request may carry, and what each grants."""

    def __init__(self, settings: Settings) -> None:
        self.required = settings.tokens_required
        self.signed = settings.jwt_configured
        self._fixed = [t.strip().encode() for t in settings.tokens.split(",") if t.strip()]
        self._file: Path | None = settings.tokens_file
        self._seen: tuple[tuple[int, int, int], list[bytes]] | None = None  # (file stamp, its tokens)
        self._lock = threading.Lock()
        self._keys, self._algorithm = _keys(settings)
        self._audience = settings.jwt_audience or None
        # A verified token's claims, by the token: a stream's or a page's token is checked once,
        # not on every request (signatures cost tens of microseconds); expiry is checked each time.
        self._verified = functools.lru_cache(maxsize=4096)(self._verify)

    def grant(self, given: bytes) -> Grant:
        """What ``given`` (a token, as bytes) grants; FULL when no token is needed.

        :raises Unauthorized: 401 without a token, or with a signed one that is expired, forged
            or malformed
        :raises Forbidden: 403 with a token that is not one this server accepts
        :raises Unavailable: 503 if the tokens file is missing or unreadable
        """
        if not self.required:
            return FULL
        accepted = self._fixed + self._from_file()
        candidate = given.strip()
        if not candidate:
            raise Unauthorized("this needs a token: send `Authorization: Bearer <token>`")
        # Compare with every token, always: the time taken says nothing about which one nearly matched.
        if sum(hmac.compare_digest(candidate, token) for token in accepted):
            return FULL
        if self.signed and candidate.count(b".") == 2:
            granted = self._verified(candidate)
            if granted.expired:
                raise Unauthorized("the token has expired: ask for a fresh one")
            return granted
        raise Forbidden("the token is not one this server accepts")

    def _verify(self, token: bytes) -> Grant:
        """The grant of a signed token whose signature, algorithm, ``exp`` and ``aud`` check out."""
        failure: jwt.PyJWTError | None = None
        for key in self._keys:
            try:
                claims = jwt.decode(
                    token,
                    key,
                    algorithms=[self._algorithm],
                    audience=self._audience,
                    options={"require": ["exp"], "verify_aud": self._audience is not None},
                )
                break
            except jwt.InvalidSignatureError as error:  # perhaps the next key of a rotation
                failure = error
            except jwt.PyJWTError as error:
                raise Unauthorized(f"the token cannot be used: {_said(error)}") from None
        else:
            raise Unauthorized(f"the token cannot be used: {_said(failure)}")
        return _grant_of(claims)

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
            raise Unavailable(message + " (VANTAGE_TOKENS_FILE)") from None


def mint(
    secret: str,
    docs: dict[str, str],
    ttl: float,
    create: bool = False,
    subject: str | None = None,
    audience: str | None = None,
) -> str:
    """A signed access token (HS256) granting ``docs`` for ``ttl`` seconds: what an app's
    backend hands its users (``vantage token`` makes one).

    >>> token = mint("x" * 32, {"d1": "read"}, 60)
    >>> sorted(jwt.decode(token, "x" * 32, algorithms=["HS256"]))
    ['docs', 'exp', 'iat']
    """
    _check_docs(docs)
    now = time.time()
    claims: dict[str, Any] = {"docs": docs, "iat": int(now), "exp": math.ceil(now + ttl)}
    if create:
        claims["create"] = True
    if subject:
        claims["sub"] = subject
    if audience:
        claims["aud"] = audience
    return jwt.encode(claims, secret.encode(), algorithm="HS256")


def _keys(settings: Settings) -> tuple[list[Any], str]:
    """The keys that verify tokens and the one algorithm they verify with.

    :raises BadKey: for a secret under 32 bytes, an unreadable PEM, or a key of no kind
        pinned here
    """
    if settings.jwt_public_key is not None:
        try:
            key = load_pem_public_key(settings.jwt_public_key.read_bytes())
        except (OSError, ValueError) as error:
            raise BadKey(
                f"VANTAGE_JWT_PUBLIC_KEY={settings.jwt_public_key}: not a PEM public key ({error})"
            ) from None
        if isinstance(key, ed25519.Ed25519PublicKey):
            return [key], "EdDSA"
        if isinstance(key, ec.EllipticCurvePublicKey) and key.curve.name == "secp256r1":
            return [key], "ES256"
        if isinstance(key, rsa.RSAPublicKey) and key.key_size >= 2048:
            return [key], "RS256"
        raise BadKey(
            "VANTAGE_JWT_PUBLIC_KEY: an Ed25519, P-256 or RSA (2048 bits or more) public key verifies "
            f"tokens, not this {type(key).__name__}"
        )
    secrets = [s.strip() for s in settings.jwt_secret.split(",") if s.strip()]
    short = [i for i, s in enumerate(secrets, 1) if len(s.encode()) < MIN_SECRET_BYTES]
    if short:
        raise BadKey(
            f"VANTAGE_JWT_SECRET: secret {short[0]} of {len(secrets)} is under {MIN_SECRET_BYTES} bytes: "
            "make each at least 32 random bytes (e.g. `openssl rand -hex 32`)"
        )
    return [s.encode() for s in secrets], "HS256"


def _grant_of(claims: dict[str, Any]) -> Grant:
    docs = claims.get("docs", {})
    try:
        _check_docs(docs)
    except ValueError as error:
        raise Unauthorized(f"the token's claims cannot be used: {error}") from None
    subject = claims.get("sub")
    return Grant(
        dict(docs),
        create=claims.get("create") is True,
        subject=str(subject) if subject is not None else None,
        expires=float(claims["exp"]),
    )


def _check_docs(docs: object) -> None:
    """:raises ValueError: unless ``docs`` maps document ids (or "*") to "read" or "write\""""
    if not isinstance(docs, dict):
        raise ValueError(
            f"`docs` is an object of document id -> 'read' or 'write', not {type(docs).__name__}"
        )
    for doc, right in docs.items():
        if right not in RIGHTS:
            raise ValueError(f"`docs` gives {doc!r} {right!r}: a right is 'read' or 'write'")


def _said(error: object) -> str:
    text = str(error) or type(error).__name__
    return {"Signature verification failed": "its signature does not match (forged, or of another key)"}.get(
        text, text[:200]
    )
