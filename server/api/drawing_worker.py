"""Drawing imports run in a worker process: bounded in time and memory, killed when over.

Parsing a drawing a user dropped is untrusted, heavy work (svgelements and ezdxf are pure
Python): it runs in a spawned process (never a fork of the running server) whose data
segment is capped by ``RLIMIT_DATA`` (:data:`MEMORY_BYTES`), and is killed after
``timeout_s``. The worker sends progress (``fraction`` 0..1) and then one result over a pipe;
the server waits on the pipe in a thread, so the event loop never blocks. A refusal
(:class:`~server.errors.DrawingError`) comes back with its message; anything else, a crash or
the time limit becomes a DrawingError that says so, and the server keeps running.
"""

from __future__ import annotations

import asyncio
import multiprocessing
import resource
from collections.abc import Callable
from multiprocessing.connection import Connection
from typing import Any

from server.errors import DrawingError

MEMORY_BYTES = 2 << 30
TIMEOUT_S = 60.0
POLL_S = 0.25


def read_task(data: bytes, name: str, width_mm: float | None, dpi: float | None,
              progress: Callable[[float], None]) -> dict[str, Any]:
    """The drawing's layers and preview (:func:`server.cam.preview.describe`)."""
    from server.cam.job import read_drawing
    from server.cam.preview import describe

    drawing = read_drawing(data, name, width_mm=width_mm, dpi=dpi)
    progress(1.0)
    return describe(drawing)


def generate_task(data: bytes, name: str, width_mm: float | None, dpi: float | None,
                  layers: dict[str, dict[str, Any]], order: list[str], max_s: float,
                  progress: Callable[[float], None]) -> dict[str, Any]:
    """The G-code of the drawing with ``layers``' settings applied (UTF-8 bytes, counted
    here: a large job's text is never encoded or scanned on the server's event loop), and
    its description."""
    from server.cam.job import make_job, read_drawing
    from server.cam.model import apply_layer_options

    drawing = read_drawing(data, name, width_mm=width_mm, dpi=dpi)
    progress(0.1)
    apply_layer_options(drawing, layers)
    drawing.reorder(order)
    gcode = make_job(drawing, max_s, lambda fraction: progress(0.1 + 0.9 * fraction))
    return {"gcode": gcode.encode(), "lines": gcode.count("\n"), "drawing": drawing.describe()}


TASKS: dict[str, Callable[..., dict[str, Any]]] = {"read": read_task, "generate": generate_task}


def _child(conn: Connection, task: str, kwargs: dict[str, Any], memory_bytes: int) -> None:
    """The worker's body: limits, the task, one message per progress step and one result."""
    resource.setrlimit(resource.RLIMIT_DATA, (memory_bytes, memory_bytes))
    try:
        result = TASKS[task](progress=lambda fraction: conn.send(("progress", fraction)),
                             **kwargs)
        conn.send(("done", result))
    except DrawingError as exc:
        conn.send(("refused", str(exc)))
    except MemoryError:
        conn.send(("refused", f"the drawing needs over {memory_bytes >> 20} MB to import"))
    except Exception as exc:  # a parser's bug on a strange file: reported, never the server's
        conn.send(("refused", f"the import failed: {type(exc).__name__}: {exc}"))
    finally:
        conn.close()


async def run(task: str, kwargs: dict[str, Any], on_progress: Callable[[float], None],
              timeout_s: float | None = None, memory_bytes: int | None = None
              ) -> dict[str, Any]:
    """``TASKS[task](**kwargs)`` in a worker process; its result. The bounds default to
    :data:`TIMEOUT_S` and :data:`MEMORY_BYTES`.

    Raises:
        DrawingError: the task refused the drawing, ran out of time or memory, or died.
    """
    timeout_s = TIMEOUT_S if timeout_s is None else timeout_s
    memory_bytes = MEMORY_BYTES if memory_bytes is None else memory_bytes
    context = multiprocessing.get_context("spawn")
    receiver, sender = context.Pipe(duplex=False)
    process = context.Process(target=_child, args=(sender, task, kwargs, memory_bytes),
                              daemon=True, name=f"motiond-import-{task}")
    await asyncio.to_thread(process.start)  # spawning and sending it the drawing take a while
    sender.close()
    loop = asyncio.get_running_loop()
    deadline = loop.time() + timeout_s
    try:
        while True:
            remaining = deadline - loop.time()
            if remaining <= 0:
                raise DrawingError(f"the import took over {timeout_s:g} s and was stopped")
            if not await asyncio.to_thread(receiver.poll, min(remaining, POLL_S)):
                continue
            try:
                kind, value = await asyncio.to_thread(receiver.recv)
            except EOFError:
                process.join(1.0)
                raise DrawingError(f"the import worker died (exit code {process.exitcode})"
                                   ) from None
            if kind == "progress":
                on_progress(float(value))
            elif kind == "done":
                return dict(value)
            else:
                raise DrawingError(str(value))
    finally:
        if process.is_alive():
            process.kill()
        await asyncio.to_thread(process.join, 5.0)
        receiver.close()
