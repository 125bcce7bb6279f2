"""Motion, pure: moves and actions (the data crossing each boundary, in mm, mm/s and s), the
look-ahead planner and its trapezoids, and the step generator's tick (its asyncio driver takes
any clock). No I/O."""
