"""Stored jobs: the files (:mod:`.store`), their plan before they start and their remaining
time while they run (:mod:`.clock`), reading them as they play (:mod:`.reading`), the one
job that plays at a time through the dispatcher (:mod:`.jobs`), and the lines a requester
runs between its lines (:mod:`.interjections`: baby-steps).

May import: ``offline``, ``machine``, ``runtime``, the pure cores, ``config``, ``paths``,
``errors``. The kernel is reached only through :class:`.jobs.JobHost`."""
