"""A Grbl, grblHAL or FluidNC controller downstream of motiond (``[backend] kind = "grbl"``)."""
