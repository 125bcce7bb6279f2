"""G-code, pure: the parser (text -> Line), the modal interpreter (Line -> moves in machine mm,
ordered actions, sync requests), arcs, and the table of M-codes modules claim. No I/O."""
