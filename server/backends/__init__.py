"""Where motion goes: the simulated machine (:mod:`.sim`), nothing (:mod:`.null`), a board
running stock Klipper MCU firmware (:mod:`.klipper`), a Grbl controller downstream with its
own machine (:mod:`.grbl`); :func:`.build.build_backend` picks one from ``[backend] kind``.

May import: ``machine`` (the Grbl host's machine builds on it), ``runtime``, the pure cores,
``config``, ``errors``."""
