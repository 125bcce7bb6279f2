"""``[klippy_api]``: Klipper's API socket for Moonraker and its front-ends (Mainsail, Fluidd,
KlipperScreen, Home Assistant). See :mod:`modules.klippy_api.module`."""

from modules.klippy_api.module import KlippyApi

__all__ = ["KlippyApi"]
