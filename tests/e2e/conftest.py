"""Fixtures the end-to-end suites share."""

from __future__ import annotations

import sys
from collections.abc import Iterator

import pytest


@pytest.fixture
def quick_thread_switches() -> Iterator[None]:
    """Senders run in threads that share the GIL with the server's loop: switch more often.
    Use with ``pytestmark = pytest.mark.usefixtures("quick_thread_switches")``."""
    before = sys.getswitchinterval()
    sys.setswitchinterval(0.0005)
    yield
    sys.setswitchinterval(before)
