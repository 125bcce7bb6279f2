"""motiond: a networked motion controller."""

__version__ = "0.1.0"
