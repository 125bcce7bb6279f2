"""Grbl's non-modal group 0 for :class:`~server.gcode.executor.LineExecutor`: G10, G28/G30 (and the
``.1`` stores), G28.2 homing, G53 and the G92 family; and M290, the babystep that shifts the
G92 offset by an amount (Klipper's ``SET_GCODE_OFFSET Z_ADJUST``).

G10 L2/L20 and G92 values are absolute (G90/G91 do not apply) and in program units. The G92
family follows LinuxCNC: G92 sets the offset (and its saved copy), G92.1 clears both, G92.2
suspends (offset zero, saved copy kept) and G92.3 restores the saved copy.
"""

from __future__ import annotations

import math

from server.errors import CommandError, Error
from server.gcode.modal import G0, G1, WCS_COUNT, Geometry, ModalState, Offsets, Words
from server.motion.moves import MoveKind, Output, Position, Sync, SyncKind


class NonModal:
    """Mixin of LineExecutor: the non-modal commands, applied to the executor's copies."""

    geo: Geometry
    words: Words
    modal: ModalState
    offsets: Offsets
    position: Position
    axes_used: bool
    values_used: set[str]
    moves: list[Output]

    def target(self) -> list[float]:
        raise NotImplementedError

    def emit(self, target: Position, kind: MoveKind, feed_mm_s: float) -> None:
        raise NotImplementedError

    def non_modal(self) -> None:
        """Apply the line's group 0 command, if any."""
        code = self.words.g("non_modal")
        if code == 100:
            self._g10()
        elif code in (280, 300):
            self._go_predefined(code)
        elif code == 281:
            self.offsets.g28 = self.position
        elif code == 301:
            self.offsets.g30 = self.position
        elif code == 282:
            self._home()
        elif code in (920, 921, 922, 923):
            self._g92(code)
        elif code == 530 and self.modal.motion not in (G0, G1):
            raise CommandError(Error.G53_MOTION_MODE, "G53 works only with G0 or G1")

    def _scaled(self, index: int, value: float) -> float:
        return value * self.geo.inch_scale[index] if self.modal.inches else value

    def _g10(self) -> None:
        values = self.words.values
        if not self.words.axes:
            raise CommandError(Error.NO_AXIS_WORDS, "G10 needs axis words")
        if "L" not in values:
            raise CommandError(Error.VALUE_WORD_MISSING, "G10 needs an L word")
        self.values_used.update("LP")
        number, kind = values.get("P", 0.0), int(values["L"])  # no P: P0, the active system
        if kind not in (2, 20):
            raise CommandError(Error.UNSUPPORTED, f"G10 L{kind} is not supported (only L2 and L20)")
        if kind == 2 and "R" in values:
            raise CommandError(Error.UNSUPPORTED, "G10 L2 R (coordinate rotation) is not supported")
        if number != int(number):
            raise CommandError(Error.INTEGER_REQUIRED, "G10 P must be an integer")
        if number > WCS_COUNT:
            raise CommandError(Error.UNSUPPORTED_WCS, f"G10 P{number:g}: P goes up to {WCS_COUNT}")
        index = int(number) - 1 if number else self.modal.wcs
        self._set_wcs(index, kind == 20)
        self.axes_used = True

    def _set_wcs(self, index: int, at_current: bool) -> None:
        """G10 L2: the offset becomes the value; L20: the current position reads as the value."""
        offsets, z = self.offsets, self.geo.z_axis
        wcs = list(offsets.wcs[index])
        for i, value in self.words.axes.items():
            mm = self._scaled(i, value)
            if at_current:
                tlo = offsets.tlo_mm if i == z else 0.0
                wcs[i] = self.position[i] - offsets.g92[i] - tlo - mm
            else:
                wcs[i] = mm
        table = list(offsets.wcs)
        table[index] = tuple(wcs)
        offsets.wcs = tuple(table)

    def _go_predefined(self, code: int) -> None:
        """G28/G30: rapid through the intermediate point (if axis words) to the stored point;
        with axis words only those axes go to the stored point."""
        stored = self.offsets.g28 if code == 280 else self.offsets.g30
        axes = self.words.axes
        self.axes_used = True
        if not axes:
            self.emit(stored, MoveKind.RAPID, math.inf)
            return
        intermediate = tuple(self.target())
        final = tuple(stored[i] if i in axes else v for i, v in enumerate(intermediate))
        self.emit(intermediate, MoveKind.RAPID, math.inf)
        self.emit(final, MoveKind.RAPID, math.inf)

    def _home(self) -> None:
        """G28.2 (Smoothieware): home the named axes (axis indices), or all (an empty list)."""
        axes = sorted(self.words.axes)
        self.axes_used = True
        self.moves.append(Sync(SyncKind.HOME, {"axes": axes}))

    def _g92(self, code: int) -> None:
        offsets, zero = self.offsets, (0.0,) * len(self.position)
        if code == 921:
            offsets.g92 = offsets.g92_saved = zero
        elif code == 922:
            offsets.g92 = zero
        elif code == 923:
            offsets.g92 = offsets.g92_saved
        else:
            self._set_g92()

    def _set_g92(self) -> None:
        """G92: the current position reads as the given values in the active system."""
        if not self.words.axes:
            raise CommandError(Error.NO_AXIS_WORDS, "G92 needs axis words")
        offsets, z = self.offsets, self.geo.z_axis
        wcs, g92 = offsets.wcs[self.modal.wcs], list(offsets.g92)
        for i, value in self.words.axes.items():
            tlo = offsets.tlo_mm if i == z else 0.0
            g92[i] = self.position[i] - wcs[i] - tlo - self._scaled(i, value)
        offsets.g92 = offsets.g92_saved = tuple(g92)
        self.axes_used = True

    def babystep(self) -> None:
        """M290 X Y Z (RepRapFirmware's and Marlin's babystep): the work offset of each named
        axis grows by the amount (program units; G92's, so a soft reset clears it) and the
        tool moves by it at once, in order with the moves queued before: the work position
        reads the same and every later move is shifted. ``P0``: the offset only, the tool
        stays (the next move that names the axis goes there), as Klipper's ``MOVE=0``."""
        if self.words.g("m_offset") is None:
            return
        axes, move = self.words.axes, self.words.values.get("P", 1.0)
        if not axes:
            raise CommandError(Error.NO_AXIS_WORDS, "M290 needs axis words")
        if move not in (0.0, 1.0):
            raise CommandError(Error.UNSUPPORTED, f"M290 P{move:g}: P0 (offset only) or P1 (move)")
        self.values_used.add("P")
        g92, target = list(self.offsets.g92), list(self.position)
        for i, value in axes.items():
            g92[i] += self._scaled(i, value)
            target[i] += self._scaled(i, value)
        why = self.geo.outside(tuple(target)) if move else None
        if why is not None:  # refused, as a jog is: a baby-step never alarms a running job
            raise CommandError(Error.JOG_TRAVEL_EXCEEDED, f"M290 target exceeds the travel: {why}")
        if move:
            self.emit(tuple(target), MoveKind.RAPID, math.inf)
        self.offsets.g92 = self.offsets.g92_saved = tuple(g92)
        self.axes_used = True
