"""Who may write, and read when so configured: bearer tokens from the settings, compared in
constant time. With no token configured, writes are open and ``vantage serve`` binds to
loopback only, so only this machine can make them."""

import hmac

from fastapi import HTTPException, Request
from starlette.requests import HTTPConnection

from .config import get_settings

__all__ = ["check", "require_read", "require_write"]

CHALLENGE = {"WWW-Authenticate": "Bearer"}


def check(connection: HTTPConnection) -> None:
    """Pass if the connection carries a configured token (or none is configured).

    :raises HTTPException: 401 without a token, 403 with a wrong one
    """
    tokens = get_settings().token_list()
    if not tokens:
        return
    header = connection.headers.get("authorization", "")
    scheme, _, given = header.partition(" ")
    if scheme.lower() != "bearer" or not given:
        given = connection.query_params.get("token", "")  # browsers cannot set a WebSocket's headers
    if not given:
        raise HTTPException(401, "this needs a token: send `Authorization: Bearer <token>`", headers=CHALLENGE)
    candidate = given.strip().encode()
    # Compare with every token, always: the time taken says nothing about which one nearly matched.
    if not sum(hmac.compare_digest(candidate, token) for token in tokens):
        raise HTTPException(403, "the token is not one this server accepts", headers=CHALLENGE)


async def require_write(request: Request) -> None:
    check(request)


async def require_read(request: Request) -> None:
    if get_settings().read_token:
        check(request)
