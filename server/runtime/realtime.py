"""Real-time scheduling for the event loop's thread: the loop gets the CPU when its timer fires.

On a host shared with senders and other programs, most late wake-ups of the event loop are not
its own work but time the OS gave to other processes: the streaming benchmark measures both
(the wall stall, and the part the loop's thread spent running). A step generator's tick, a
feed hold and a status report cannot wait for the scheduler's next round, so ``motiond serve``
asks Linux for a real-time policy (``SCHED_FIFO``) for the loop's thread, as LinuxCNC and
Klipper's Linux MCU process do for their step timing:

* the loop preempts ordinary processes the moment it wakes, so a stall is its own work only;
* ``SCHED_RESET_ON_FORK``: the processes and threads it starts (a worker thread planning a
  toolpath or writing settings) run at ordinary priority and never compete with the loop;
* the interpreter's GIL switch interval drops to 0.5 ms, so a worker thread running Python
  hands the GIL back to the loop within that, not the default 5 ms;
* Linux keeps 5 % of every second for ordinary processes (``sched_rt_runtime_us``), so even a
  runaway loop cannot lock the host up.

Only on asyncio's own event loop: uvloop (libuv) rounds timers to whole milliseconds, so a loop
waiting less than that polls without sleeping until the time comes; a real-time thread that
polls uses up Linux's real-time budget and is then stopped for the rest of the second (50 ms
stalls, measured). asyncio's loop, on :mod:`server.runtime.selector`, sleeps to the
microsecond instead. So ``--loop auto`` takes asyncio's loop whenever real-time priority is
allowed (it then keeps the stall goal with other programs busy, which uvloop at ordinary
priority does not, measured), and uvloop when installed only otherwise.

Without the right (``CAP_SYS_NICE``, an ``rtprio`` limit, Docker's ``--ulimit rtprio=10``)
motiond runs at ordinary priority and says so once.
"""

from __future__ import annotations

import asyncio
import os
import sys
import threading
from dataclasses import dataclass

GIL_SWITCH_INTERVAL_S = 0.0005
HOW_TO_GRANT = (
    "grant it with `setcap cap_sys_nice+ep` on the Python binary, an `rtprio` limit in "
    "/etc/security/limits.conf, `--ulimit rtprio=10` (Docker) or `CPUSchedulingPolicy=fifo` "
    "(systemd); or set [stepgen] realtime_priority = 0 to stop asking"
)


@dataclass(frozen=True, slots=True)
class Priority:
    """What the loop's thread runs at: ``priority`` 0 is the ordinary time-shared policy."""

    priority: int
    detail: str

    @property
    def realtime(self) -> bool:
        return self.priority > 0


def claim(priority: int) -> Priority:
    """Run the calling thread (the event loop's) at real-time ``priority`` (1-99) under
    ``SCHED_FIFO``; 0 leaves it as it is. Never raises: the result says what it got."""
    if priority <= 0:
        return Priority(0, "ordinary priority ([stepgen] realtime_priority = 0)")
    if not hasattr(os, "sched_setscheduler"):
        return Priority(0, "ordinary priority (real-time scheduling needs Linux)")
    policy = os.SCHED_FIFO | os.SCHED_RESET_ON_FORK
    try:
        os.sched_setscheduler(0, policy, os.sched_param(priority))
    except OSError as exc:
        return Priority(0, f"ordinary priority: real-time priority refused ({exc.strerror}); "
                           + HOW_TO_GRANT)
    sys.setswitchinterval(GIL_SWITCH_INTERVAL_S)
    return Priority(priority, f"real-time priority {priority} (SCHED_FIFO)")


def allowed(priority: int) -> bool:
    """Whether this process may run a thread at real-time ``priority`` (tried in a throw-away
    thread, whose policy ends with it)."""
    if priority <= 0 or not hasattr(os, "sched_setscheduler"):
        return False
    granted: list[bool] = []

    def attempt() -> None:
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
        except OSError:
            granted.append(False)
        else:
            granted.append(True)

    thread = threading.Thread(target=attempt, name="realtime-check")
    thread.start()
    thread.join()
    return granted[0]


def claim_for(loop: asyncio.AbstractEventLoop, priority: int) -> Priority:
    """:func:`claim` for the thread running ``loop``, if it is asyncio's own (see the module
    docstring); another loop keeps the ordinary policy and says why."""
    if priority > 0 and not isinstance(loop, asyncio.BaseEventLoop):
        return Priority(0, f"ordinary priority (no real-time priority on {type(loop).__name__}: "
                           "its millisecond timers can poll, and a polling real-time thread is "
                           "stopped by Linux for the rest of the second)")
    return claim(priority)


def release(previous_switch_interval_s: float) -> None:
    """Back to the ordinary policy (benchmarks compare both in one process)."""
    if hasattr(os, "sched_setscheduler"):
        os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
    sys.setswitchinterval(previous_switch_interval_s)
