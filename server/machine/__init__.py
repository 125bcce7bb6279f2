"""The planned machine: the motion pipeline (interpreter -> planner -> step generator ->
backend) with its G-code feed (:mod:`.feed`), its realtime controls (hold, resume, reset,
stops, overrides: :mod:`.controls`), its parts from the config (:mod:`.parts`) and Grbl's
numbered settings (:mod:`.settings`).

May import: ``runtime``, the pure cores, ``config``, ``paths``, ``errors``; the backend only
through its interface (:mod:`server.motion.backend`): which backend is built is the kernel's
choice, and a backend's own machine (:mod:`server.backends.grbl.machine`) builds on this one."""
