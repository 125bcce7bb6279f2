"""The JSON-RPC API over WebSocket (``/api``, ``/upload``): its decoder, its method tables
composed with what modules contribute, and the telemetry it pushes."""
