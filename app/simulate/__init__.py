"""The panning simulator: virtual users pan a document the way people do, in each mode the
service offers, and the report says what they would see: latency, bytes and blank area."""

from .run import main

__all__ = ["main"]
