"""The event loop's selector: waits to the microsecond, events as epoll reports them."""

from __future__ import annotations

import asyncio
import select
import selectors
import socket
from collections.abc import Iterator
from typing import Any

import pytest

from server.runtime import selector as fine
from server.runtime.selector import FineEpollSelector, asyncio_loop


class PollSpy:
    """Stands in for the selector's epoll object, recording the timeouts it is polled with."""

    def __init__(self, epoll: Any) -> None:
        self.epoll, self.timeouts = epoll, []

    def poll(self, timeout: float = -1, maxevents: int = -1) -> Any:
        self.timeouts.append(timeout)
        return self.epoll.poll(timeout, maxevents)

    def __getattr__(self, name: str) -> Any:
        return getattr(self.epoll, name)


@pytest.fixture
def pair() -> Iterator[tuple[socket.socket, socket.socket]]:
    left, right = socket.socketpair()
    yield left, right
    left.close()
    right.close()


def spied(monkeypatch: pytest.MonkeyPatch) -> tuple[FineEpollSelector, PollSpy, list[float]]:
    waits: list[float] = []

    def recording_select(r: Any, w: Any, x: Any, timeout: float) -> Any:
        waits.append(timeout)
        return select.select(r, w, x, timeout)

    monkeypatch.setattr(fine, "select", type("Select", (), {"select": recording_select}))
    chosen = FineEpollSelector()
    spy = PollSpy(chosen._selector)  # type: ignore[attr-defined]
    chosen._selector = spy  # type: ignore[attr-defined]
    return chosen, spy, waits


def test_a_wait_under_a_millisecond_is_not_rounded_up_to_one(
    monkeypatch: pytest.MonkeyPatch, pair: tuple[socket.socket, socket.socket]
) -> None:
    chosen, spy, waits = spied(monkeypatch)
    chosen.register(pair[0], selectors.EVENT_READ)
    assert chosen.select(0.0003) == []
    assert waits == [0.0003], "select() waited the exact time"
    assert spy.timeouts == [], "and timed out: nothing to collect, no epoll_wait (a syscall)"
    chosen.close()


def test_what_woke_the_wait_is_collected_from_epoll_without_waiting(
    monkeypatch: pytest.MonkeyPatch, pair: tuple[socket.socket, socket.socket]
) -> None:
    chosen, spy, waits = spied(monkeypatch)
    key = chosen.register(pair[0], selectors.EVENT_READ)
    pair[1].send(b"x")
    assert chosen.select(5.0) == [(key, selectors.EVENT_READ)]
    assert spy.timeouts == [0], "epoll only collected what was ready"
    chosen.close()


def test_ready_descriptors_are_reported_as_epoll_reports_them(
    pair: tuple[socket.socket, socket.socket]
) -> None:
    chosen = FineEpollSelector()
    key = chosen.register(pair[0], selectors.EVENT_READ, data="reader")
    pair[1].send(b"x")
    assert chosen.select(5.0) == [(key, selectors.EVENT_READ)]
    assert chosen.select(0) == [(key, selectors.EVENT_READ)], "still unread: still ready"
    pair[0].recv(1)
    assert chosen.select(0) == []
    chosen.close()


def test_no_wait_and_no_limit_on_descriptors_falls_back_to_epoll(
    monkeypatch: pytest.MonkeyPatch
) -> None:
    chosen, spy, waits = spied(monkeypatch)
    assert chosen.select(0) == [] and waits == []  # a poll: nothing to wait for
    monkeypatch.setattr(fine, "FD_SETSIZE", 0)  # as if the epoll descriptor were beyond it
    assert chosen.select(0.0003) == []
    assert waits == [] and spy.timeouts[-1] > 0, "epoll waited itself"
    chosen.close()


def test_the_asyncio_loop_of_serve_runs_on_it_and_serves_sockets() -> None:
    loop = asyncio_loop()
    try:
        assert isinstance(loop._selector, FineEpollSelector)  # type: ignore[attr-defined]

        async def echo_once() -> bytes:
            async def handle(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
                writer.write(await reader.readline())
                await writer.drain()
                writer.close()

            server = await asyncio.start_server(handle, "127.0.0.1", 0)
            port = server.sockets[0].getsockname()[1]
            reader, writer = await asyncio.open_connection("127.0.0.1", port)
            writer.write(b"?\n")
            await asyncio.sleep(0.0002)  # a sub-millisecond timer on the way
            line = await reader.readline()
            writer.close()
            server.close()
            return line

        assert loop.run_until_complete(echo_once()) == b"?\n"
    finally:
        loop.close()
