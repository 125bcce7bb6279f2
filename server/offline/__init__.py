"""Offline runs of the live pipeline on virtual time: ``estimate``, ``render`` and the planned
toolpath the web UI draws."""
