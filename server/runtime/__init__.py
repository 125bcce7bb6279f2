"""The running machine: the kernel (modules, supervision, events), the machine state's owner,
the motion pipeline and its controls, the dispatcher's ordered stream, settings, jobs, the
clocks, and the per-connection session that transports feed."""
