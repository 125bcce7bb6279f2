"""The Klipper backend: stock Klipper MCU firmware executing host-timed ``queue_step``.

Pure cores (no I/O): :mod:`.codec` (framing, VLQ, the data dictionary), :mod:`.clocksync`
(host seconds to MCU ticks), :mod:`.steptimes` (exact step times of a trajectory piece),
:mod:`.stepcompress` (step times to ``queue_step`` triplets); :mod:`.link` is the serial
transport (its own thread in ``_serialq.c`` owns the device) and :mod:`.backend` the
:class:`~server.motion.backend.Backend`, composed of its step schedule (:mod:`.schedule`),
its outputs' timing (:mod:`.outputs`) and its session with the board (:mod:`.session`).
"""
