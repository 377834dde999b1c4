"""Dependency aliases the routers share.

They are ``async def``: FastAPI runs a plain ``def`` dependency in the thread pool, a hop that
costs more than the lookups themselves.
"""

from collections.abc import AsyncIterator
from typing import Annotated

from fastapi import Depends, Request

from .config import Settings
from .documents import Document
from .registry import Registry

__all__ = ["DocumentDep", "MediaTypeDep", "RegistryDep", "SettingsDep"]


async def _registry(request: Request) -> Registry:
    return request.app.state.registry


async def _document(doc: str, request: Request) -> AsyncIterator[Document]:
    """The document, open and up to date, kept open until the answer is sent."""
    registry: Registry = request.app.state.registry
    document = await registry.get(doc)
    with registry.pinned(document):
        yield document


async def _settings(request: Request) -> Settings:
    return request.app.state.settings


async def _media_type(request: Request) -> str:
    """The body's media type, as the ``Content-Type`` header names it: lower case, no parameters."""
    return request.headers.get("content-type", "").partition(";")[0].strip().lower()


RegistryDep = Annotated[Registry, Depends(_registry)]
DocumentDep = Annotated[Document, Depends(_document)]
SettingsDep = Annotated[Settings, Depends(_settings)]
MediaTypeDep = Annotated[str, Depends(_media_type)]
