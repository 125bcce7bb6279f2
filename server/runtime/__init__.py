"""The running machine's shared parts, below everything that runs: the clocks (real and
virtual), the event bus, the machine state with its alarm and the stop generation
(:mod:`.state`), the step generator's ticks, the dispatcher's one ordered command stream
(:mod:`.dispatcher`, :mod:`.turn`), rate limits, garbage-collection pacing, and the process's
real-time priority, timer resolution and systemd readiness.

May import: the pure cores (``gcode``, ``motion``, ``protocol``), ``errors``, ``config``.
Nothing here knows a machine, a session, a job or the kernel."""
