"""The command line, ``motiond``: serving (:mod:`.main`), and the offline commands
``estimate`` and ``render`` (:mod:`.offline`). The top of the tree: nothing imports it."""

from server.cli.main import main

__all__ = ["main"]
