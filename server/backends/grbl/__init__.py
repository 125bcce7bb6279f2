"""A Grbl, grblHAL or FluidNC controller downstream of motiond (``[backend] kind = "grbl"``):
the serial link and its reports (:mod:`.link`, :mod:`.reports`), the controller that streams
to the board (:mod:`.controller`), and the machine that hosts it (:mod:`.machine`, a
:class:`server.machine.machine.Machine` whose motion the board plans), with what it adopts
from the board (:mod:`.adopt`), its journal of refused lines (:mod:`.journal`) and the board's
own messages made safe (:mod:`.feedback`)."""
