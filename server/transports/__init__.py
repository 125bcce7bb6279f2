"""Transports: thin adapters that move bytes between clients and sessions (TCP, serial and
the pty, WebSocket and static HTTP). They know sessions and the kernel, never the JSON API
or the app; which of them run is the app's choice (:func:`server.app.default_transports`)."""
