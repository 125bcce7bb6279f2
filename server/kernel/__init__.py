"""The kernel: the composition of one running machine. :mod:`.kernel` builds the machine,
its backend, the dispatcher, the jobs and the modules and supervises their tasks; the module
contract (:mod:`.module`), the core's commands (:mod:`.commands`), the one implementation of
hold, resume, reset and emergency stop for every entry point (:mod:`.control`), the status
every client reads (:mod:`.status`) and the event loop's stall monitor (:mod:`.loop_monitor`).

May import: ``jobs``, ``offline``, ``backends``, ``machine``, ``runtime``, the pure cores,
``config``, ``paths``, ``errors``. Never sessions, transports, the API or the app."""
