"""Input held back while a connection's line queue is full, with its realtime bytes found at once.

Grbl acts on ``!``, ``~``, ``?``, Ctrl-X and the extended bytes the moment they arrive, even
when its serial buffer is full; motiond does the same on every transport (TCP, serial, pty and
WebSocket messages alike). A sender that streams ahead without character counting fills
motiond's line queue; if the transport stopped reading then, a later ``!`` would wait behind
the whole stream. So the session keeps taking bytes into a :class:`Backlog`, bounded in bytes:

* the bytes are kept as they came, to be fed to the connection's protocol when lines drain;
* a twin of the protocol (:meth:`LineProtocol.copy`, taken when the backlog starts) reads them
  at once, so realtime bytes are recognised exactly as the protocol will later see them
  (dialect, UTF-8 continuation bytes, ``C2``-prefixed commands), and the session acts on them;
  when the held bytes are fed to the protocol later, their realtime events are ignored;
* Ctrl-X never reaches the backlog: the session splits input at ``0x18`` (always a reset,
  whatever precedes it) and drops everything held before it, as Grbl empties its buffer.

Only when the backlog holds ``limit_bytes`` does the transport stop reading (the TCP window
then fills); realtime bytes already received are still acted on.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable

from server.protocol.events import Event
from server.protocol.lines import LineProtocol


class Backlog:
    """Bytes not yet fed to the protocol, and the twin protocol that has already read them.

    Bytes are kept in segments: a WebSocket message's last part ends a segment (``final``:
    the message's end ends its last line), so they are fed to the protocol as they came;
    a byte stream's bytes form one segment."""

    def __init__(self, limit_bytes: int) -> None:
        self.limit_bytes = limit_bytes
        self._segments: deque[tuple[bytearray, bool]] = deque()
        self._size = 0
        self._twin: LineProtocol | None = None

    def __len__(self) -> int:
        return self._size

    @property
    def full(self) -> bool:
        return self._size >= self.limit_bytes

    def hold(self, protocol: LineProtocol, data: bytes, final: bool = False,
             keep: Callable[[bytes], bool] | None = None) -> list[Event]:
        """Keep ``data`` (no ``0x18`` in it) after what is held; return what the twin of
        ``protocol`` finds in it: realtime commands to act on now, and lines only to look at,
        those ``keep`` asks for (:meth:`LineProtocol.receive_ahead`: the others are not even
        built, so holding a stream back costs little whatever its size).
        ``final``: the end of a WebSocket message."""
        if b"\x18" in data:
            raise ValueError("Ctrl-X is never held back: split the input at it")
        if not data:
            return []
        if self._twin is None:
            self._twin = protocol.copy()
        if self._segments and not self._segments[-1][1]:
            self._segments[-1][0].extend(data)
            self._segments[-1] = (self._segments[-1][0], final)
        else:
            self._segments.append((bytearray(data), final))
        self._size += len(data)
        return self._twin.receive_ahead(data, final=final, keep=keep)

    def take(self, size_bytes: int) -> tuple[bytes, bool]:
        """The oldest held bytes, at most ``size_bytes``, for the protocol itself, and whether
        they end a WebSocket message."""
        segment, final = self._segments[0]
        piece = bytes(segment[:size_bytes])
        del segment[:size_bytes]
        self._size -= len(piece)
        if segment:
            final = False
        else:
            self._segments.popleft()
        if not self._segments:
            self._twin = None  # the protocol has caught up with its twin
        return piece, final

    def clear(self) -> None:
        self._segments.clear()
        self._size = 0
        self._twin = None
