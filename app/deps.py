"""Dependency aliases the routers share."""

from typing import Annotated

from fastapi import Depends, Request

from .config import Settings, get_settings
from .documents import Document, Registry

__all__ = ["DocumentDep", "RegistryDep", "SettingsDep"]


def get_registry(request: Request) -> Registry:
    return request.app.state.registry


def get_document(doc: str, request: Request) -> Document:
    return request.app.state.registry[doc]


RegistryDep = Annotated[Registry, Depends(get_registry)]
DocumentDep = Annotated[Document, Depends(get_document)]
SettingsDep = Annotated[Settings, Depends(get_settings)]
