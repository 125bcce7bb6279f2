"""The compiled parts: the Klipper backend's step core and the G-code parser's plain words;
the metadata is in pyproject.toml.

Both are optional: without a C compiler and Python's headers motiond still installs and runs
the simulated machine, the parser reads every line on its general path (slower, alike), and
the Klipper backend refuses to start, naming what to install.
"""

from setuptools import Extension, setup

setup(ext_modules=[Extension(
    "server.backends.klipper._stepcore",
    sources=["server/backends/klipper/_stepcore.c", "server/backends/klipper/_wire.c",
             "server/backends/klipper/_stepaxis.c", "server/backends/klipper/_movequeue.c",
             "server/backends/klipper/_serialq.c", "server/backends/klipper/_serialq_thread.c"],
    depends=["server/backends/klipper/_serialq.h", "server/backends/klipper/_stepcore.h"],
    extra_compile_args=["-O2", "-ffp-contract=off", "-pthread"],  # (-ffp-contract=off: no
    extra_link_args=["-pthread"],  # fused multiply-add: exact roundings)
    optional=True,
), Extension(
    "server.gcode._words",
    sources=["server/gcode/_words.c"],
    extra_compile_args=["-O2"],
    optional=True,
)])
