"""`prop serve`: a bundle as a long-running policy server speaking openpi's websocket protocol, so
``openpi_client.websocket_client_policy.WebsocketClientPolicy`` connects unchanged. Each connection
brings its user's key (the ``Authorization: Api-Key`` header), checked once; an array model's requests of
many users run as one forward of the base, each row its own user's behaviour (docs/serving.md)."""

from .server import PolicyServer, Running, serve_bundle, start_in_thread
from .wire import WireError, packb, unpackb

__all__ = ["PolicyServer", "Running", "WireError", "packb", "serve_bundle", "start_in_thread", "unpackb"]
