"""The Klipper backend's compiled step core; the metadata is in pyproject.toml.

The extension is optional: without a C compiler and Python's headers motiond still installs
and runs the simulated machine, and the Klipper backend refuses to start, naming what to install.
"""

from setuptools import Extension, setup

setup(ext_modules=[Extension(
    "server.backends.klipper._stepcore",
    sources=["server/backends/klipper/_stepcore.c", "server/backends/klipper/_wire.c",
             "server/backends/klipper/_serialq.c", "server/backends/klipper/_serialq_thread.c"],
    depends=["server/backends/klipper/_serialq.h"],
    extra_compile_args=["-O2", "-ffp-contract=off", "-pthread"],  # (-ffp-contract=off: no
    extra_link_args=["-pthread"],  # fused multiply-add: exact roundings)
    optional=True,
)])
