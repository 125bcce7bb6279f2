"""The backend named by ``[backend] kind``: where the step generator's motion goes."""

from __future__ import annotations

from server.backends.null import NullBackend
from server.backends.sim import SimBackend
from server.config import CoreConfig
from server.motion.backend import Backend


def build_backend(core: CoreConfig) -> Backend:
    """The backend named by ``[backend] kind``."""
    if core.backend.kind in ("null", "grbl"):  # a Grbl controller steps itself
        return NullBackend()
    if core.backend.kind == "klipper":
        from server.backends.klipper.backend import KlipperBackend  # only when configured

        return KlipperBackend(core)
    return SimBackend(
        core.axis_names,
        [axis.steps_per_mm for axis in core.axes.values()],
        history_samples=core.backend.history_samples,
        trace_csv=core.backend.trace_csv,
        probe_at_mm=core.backend.probe_at_mm,
    )
