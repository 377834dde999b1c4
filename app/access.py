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

Every refusal is in the server's own words (the constants below), never the JWT library's: a
client reads the reason, and the library's text ("Invalid crypto padding") says nothing to it.
"""

from __future__ import annotations

import base64
import binascii
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
import orjson
from cryptography.hazmat.primitives.asymmetric import ec, ed25519, rsa
from cryptography.hazmat.primitives.serialization import load_pem_public_key

from .config import Settings
from .errors import Forbidden, Unauthorized, Unavailable

__all__ = ["Access", "BadKey", "FULL", "Grant", "hmac_secrets", "mint"]

MIN_SECRET_BYTES = 32  # HS256's key: as long as its hash (RFC 7518 section 3.2)
RIGHTS = ("read", "write")

NO_TOKEN = "this needs a token: send `Authorization: Bearer <token>`"
EXPIRED = "the token has expired: ask for a fresh one"
FORGED = "the token's signature does not verify (forged, or signed with another key)"
UNREADABLE = (
    "the token is neither one of this server's tokens nor a signed token it can read "
    "(a JWT: three base64url parts joined by dots)"
)
UNKNOWN = "the token is not one this server accepts"


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
        # Reads need a token: no shared cache (a CDN's) may keep what they answer
        self.reads_private = bool(settings.jwt_configured or settings.read_token)
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

        :raises Unauthorized: 401 without a token; with a JWT key, any token that is neither a
            static one nor a valid signed one (expired, forged, malformed...)
        :raises Forbidden: 403 with a token that is not one this server accepts (no JWT key)
        :raises Unavailable: 503 if the tokens file is missing or unreadable
        """
        if not self.required:
            return FULL
        accepted = self._fixed + self._from_file()
        candidate = given.strip()
        if not candidate:
            raise Unauthorized(NO_TOKEN)
        # Compare with every token, always: the time taken says nothing about which one nearly matched.
        if sum(hmac.compare_digest(candidate, token) for token in accepted):
            return FULL
        if self.signed:  # whatever it is, it is not a valid token: 401, saying why
            granted = self._verified(candidate)
            if granted.expired:  # verified while valid, then cached: its `exp` still counts
                raise Unauthorized(EXPIRED)
            return granted
        raise Forbidden(UNKNOWN)

    def _verify(self, token: bytes) -> Grant:
        """The grant of a signed token whose signature, algorithm, ``exp`` and ``aud`` check out."""
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
            except jwt.InvalidSignatureError:  # perhaps the next key of a rotation
                continue
            except jwt.PyJWTError as error:
                raise Unauthorized(self._refusal(error, token)) from None
        else:
            raise Unauthorized(FORGED)
        return _grant_of(claims)

    def _refusal(self, error: jwt.PyJWTError, token: bytes) -> str:
        """Why ``token`` is refused, in this server's words."""
        if isinstance(error, jwt.ExpiredSignatureError):
            return EXPIRED
        if isinstance(error, jwt.ImmatureSignatureError):
            return "the token is not valid yet: its `nbf` or `iat` is in the future"
        if isinstance(error, jwt.MissingRequiredClaimError) and error.claim == "exp":
            return "the token has no `exp` claim: a signed token must say when it expires"
        if isinstance(error, (jwt.MissingRequiredClaimError, jwt.InvalidAudienceError)):
            return "the token's `aud` claim does not name this server's audience (VANTAGE_JWT_AUDIENCE)"
        if isinstance(error, jwt.InvalidAlgorithmError):
            return f"the token's `alg` is not {self._algorithm}, the one algorithm this server's key verifies"
        parts = token.split(b".")
        if len(parts) != 3 or any(_json_object(part) is None for part in parts[:2]):
            return UNREADABLE
        if _unbase64(parts[2]) is None:  # its header and claims read, its signature does not
            return FORGED
        # Signed, but a registered claim is not of its type (PyJWT checks them after the signature)
        return (
            "the token's claims cannot be used: `exp`, `nbf` and `iat` are numbers, `sub` and `iss` strings"
        )

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
    return hmac_secrets(settings.jwt_secret), "HS256"


def hmac_secrets(setting: str) -> list[bytes]:
    """The secrets of ``VANTAGE_JWT_SECRET`` (comma-separated), each checked: the one rule, and
    its message, for the server that verifies and ``vantage token`` that signs.

    :raises BadKey: for a secret under 32 bytes
    """
    secrets = [s.strip().encode() for s in setting.split(",") if s.strip()]
    short = [i for i, s in enumerate(secrets, 1) if len(s) < MIN_SECRET_BYTES]
    if short:
        raise BadKey(
            f"VANTAGE_JWT_SECRET: secret {short[0]} of {len(secrets)} is under {MIN_SECRET_BYTES} bytes: "
            f"make each at least {MIN_SECRET_BYTES} random bytes (e.g. `openssl rand -hex 32`)"
        )
    return secrets


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


def _unbase64(part: bytes) -> bytes | None:
    """``part`` base64url-decoded (as a JWT writes it: unpadded), or None if it is not that."""
    try:
        return base64.b64decode(part + b"=" * (-len(part) % 4), altchars=b"-_", validate=True)
    except (binascii.Error, ValueError):
        return None


def _json_object(part: bytes) -> dict | None:
    """``part`` decoded as a JWT's header or claims: a JSON object, or None."""
    raw = _unbase64(part)
    try:
        decoded = orjson.loads(raw) if raw is not None else None
    except orjson.JSONDecodeError:
        return None
    return decoded if isinstance(decoded, dict) else None
