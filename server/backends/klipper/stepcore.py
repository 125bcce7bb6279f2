"""The compiled step core (``_stepcore.c``): step times and their compression, each stepper's
steps held until due and sent (``_stepaxis.c``: :class:`StepAxis`), the MCU's move queue as
the host counts it (``_movequeue.c``: :class:`MoveQueueCore`), the wire's hot end (a
prepared message's VLQs, a block's framing and checksum) and the link's thread (``_serialq.c``:
:class:`SerialQueue`).

``pip install`` builds it when a C compiler and Python's headers are there; it is optional so
that motiond installs without them (the simulated machine needs no core). Without it the Klipper
backend refuses to start, as a configuration problem naming what to install.
"""

from __future__ import annotations

from server.errors import ConfigError

MISSING = ('[backend] kind = "klipper" needs the compiled step core, which was not built: '
           "sudo apt install gcc python3-dev, then pip install -e . again")

try:
    from server.backends.klipper._stepcore import (
        ADD_MAX,
        ADD_MIN,
        MAX_COUNT,
        MAX_TRIES,
        QUADRATIC_DEV,
        WINDOW,
        MoveQueueCore,
        SerialQueue,
        StepAxis,
        compress,
        crc16,
        frame,
        message,
        off_track,
        piece_steps,
        solve,
    )
except ImportError:
    raise ConfigError([MISSING]) from None

__all__ = ["ADD_MAX", "ADD_MIN", "MAX_COUNT", "MAX_TRIES", "QUADRATIC_DEV", "WINDOW",
           "MoveQueueCore", "SerialQueue", "StepAxis", "compress", "crc16", "frame", "message",
           "off_track", "piece_steps", "solve"]
