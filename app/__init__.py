"""Vantage's viewport service: documents held in a quadtree, answered over HTTP and WebSocket."""

__all__: list[str] = []  # a package of modules: each declares its own
