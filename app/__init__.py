"""Vantage's viewport service: documents held in a quadtree, answered over HTTP and WebSocket."""
