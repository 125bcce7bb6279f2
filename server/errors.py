"""The one exception tree of motiond, and the one table of its error and alarm numbers.

Two kinds of error (STYLE.md habit 10): a :class:`CommandError` is answered to its sender as
``error:N`` and changes nothing; anything else unexpected alarms the machine (``ALARM:N``).
:class:`Error` and :class:`Alarm` hold every number motiond uses: Grbl 1.1's, then motiond's
own above 38 (Grbl leaves them free); :data:`ERROR_MEANINGS` and :data:`ALARM_MEANINGS` say
what each means to the people reading a sender's console.
"""

from __future__ import annotations

import enum


class Error(enum.IntEnum):
    """``error:N`` numbers (Grbl 1.1, then motiond's own)."""

    EXPECTED_COMMAND_LETTER = 1
    BAD_NUMBER_FORMAT = 2
    INVALID_STATEMENT = 3
    NEGATIVE_VALUE = 4
    SETTING_DISABLED = 5
    NOT_IDLE = 8
    LOCKED_OUT = 9
    SOFT_LIMITS_NEED_HOMING = 10
    LINE_OVERFLOW = 11
    JOG_TRAVEL_EXCEEDED = 15
    INVALID_JOG = 16
    UNSUPPORTED = 20
    MODAL_GROUP_VIOLATION = 21
    UNDEFINED_FEED = 22
    INTEGER_REQUIRED = 23
    AXIS_COMMAND_CONFLICT = 24
    REPEATED_WORD = 25
    NO_AXIS_WORDS = 26
    INVALID_LINE_NUMBER = 27
    VALUE_WORD_MISSING = 28
    UNSUPPORTED_WCS = 29
    G53_MOTION_MODE = 30
    UNUSED_AXIS_WORDS = 31
    NO_AXIS_WORDS_IN_PLANE = 32
    INVALID_TARGET = 33
    ARC_RADIUS_ERROR = 34
    NO_OFFSETS_IN_PLANE = 35
    UNUSED_VALUE_WORDS = 36
    TLO_AXIS = 37
    TOOL_NUMBER = 38
    SOFT_LIMIT = 40
    CHECKSUM = 41
    LINE_NUMBER_SEQUENCE = 42
    UNKNOWN_COMMAND = 43
    FILE_ERROR = 44
    BUSY = 45
    AUTH_REQUIRED = 46
    JOB_DOES_NOT_FIT = 47
    SETTING_NOT_SAVED = 48


class Alarm(enum.IntEnum):
    """``ALARM:N`` numbers (Grbl 1.1, then motiond's own)."""

    HARD_LIMIT = 1
    SOFT_LIMIT = 2
    ABORT_CYCLE = 3
    PROBE_INITIAL = 4
    PROBE_CONTACT = 5
    HOMING_RESET = 6
    HOMING_DOOR = 7
    HOMING_PULL_OFF = 8
    HOMING_NOT_FOUND = 9
    HOMING_DUAL = 10
    HALT = 40
    MODULE_FAILED = 41
    BACKEND_FAILED = 42


ERROR_MEANINGS: dict[int, str] = {
    Error.EXPECTED_COMMAND_LETTER: "Expected command letter",
    Error.BAD_NUMBER_FORMAT: "Bad number format",
    Error.INVALID_STATEMENT: "Invalid $ statement",
    Error.NEGATIVE_VALUE: "Negative value",
    Error.SETTING_DISABLED: "Setting disabled",
    Error.NOT_IDLE: "Not idle",
    Error.LOCKED_OUT: "G-code locked out during alarm or jog",
    Error.SOFT_LIMITS_NEED_HOMING: "Soft limits need homing enabled",
    Error.LINE_OVERFLOW: "Line overflow",
    Error.JOG_TRAVEL_EXCEEDED: "Jog target exceeds machine travel",
    Error.INVALID_JOG: "Invalid jog command",
    Error.UNSUPPORTED: "Unsupported or invalid G-code command",
    Error.MODAL_GROUP_VIOLATION: "Modal group violation",
    Error.UNDEFINED_FEED: "Undefined feed rate",
    Error.INTEGER_REQUIRED: "Integer value required",
    Error.AXIS_COMMAND_CONFLICT: "Two commands need axis words",
    Error.REPEATED_WORD: "Repeated word",
    Error.NO_AXIS_WORDS: "No axis words",
    Error.INVALID_LINE_NUMBER: "Invalid line number",
    Error.VALUE_WORD_MISSING: "Missing P or L value",
    Error.UNSUPPORTED_WCS: "Unsupported work coordinate system",
    Error.G53_MOTION_MODE: "G53 only with G0 or G1",
    Error.UNUSED_AXIS_WORDS: "Unused axis words",
    Error.NO_AXIS_WORDS_IN_PLANE: "G2/G3 need an in-plane axis word",
    Error.INVALID_TARGET: "Invalid motion target",
    Error.ARC_RADIUS_ERROR: "Arc radius error",
    Error.NO_OFFSETS_IN_PLANE: "G2/G3 offset form needs an in-plane IJK word",
    Error.UNUSED_VALUE_WORDS: "Unused value words",
    Error.TLO_AXIS: "Tool length offset not on the tool axis",
    Error.TOOL_NUMBER: "Tool number too large",
    Error.SOFT_LIMIT: "target outside the machine's travel (soft limit); ALARM:2 raised",
    Error.CHECKSUM: "checksum mismatch; the line was not executed",
    Error.LINE_NUMBER_SEQUENCE: "line number out of sequence",
    Error.UNKNOWN_COMMAND: "unknown command",
    Error.FILE_ERROR: "job file missing, unreadable or outside the data directory",
    Error.BUSY: "refused while a job or another connection's motion runs",
    Error.AUTH_REQUIRED: "this connection may not control the machine",
    Error.JOB_DOES_NOT_FIT: "the job does not fit the travel from the current work origin; "
    "nothing moved",
    Error.SETTING_NOT_SAVED: "the setting could not be saved (a full disk, a read-only "
    "folder): the old value is kept",
}

ALARM_MEANINGS: dict[int, str] = {
    Alarm.HARD_LIMIT: "Hard limit triggered; position may be lost, home again",
    Alarm.SOFT_LIMIT: "Soft limit: the motion target exceeds the machine travel; position kept",
    Alarm.ABORT_CYCLE: "Reset while in motion; position may be lost, home again",
    Alarm.PROBE_INITIAL: "Probe fail: the probe is not in the expected initial state",
    Alarm.PROBE_CONTACT: "Probe fail: the probe did not contact within the search distance",
    Alarm.HOMING_RESET: "Homing fail: reset during the homing cycle",
    Alarm.HOMING_DOOR: "Homing fail: safety door opened during homing",
    Alarm.HOMING_PULL_OFF: "Homing fail: pull-off did not clear the limit switch",
    Alarm.HOMING_NOT_FOUND: "Homing fail: limit switch not found within the search distance",
    Alarm.HOMING_DUAL: "Homing fail: second switch of a dual axis not found",
    Alarm.HALT: "Halt (M112 or emergency stop): motion stopped, tools off",
    Alarm.MODULE_FAILED: "A module failed: motion stopped, tools off",
    Alarm.BACKEND_FAILED: "The machine backend failed: motion stopped, tools off",
}


class MotiondError(Exception):
    """Base class of every error motiond raises on purpose."""


class ConfigError(MotiondError):
    """A configuration file is invalid. ``problems`` holds one readable line per problem."""

    def __init__(self, problems: list[str]) -> None:
        super().__init__("\n".join(problems))
        self.problems = problems


class CommandError(MotiondError):
    """A line or command was refused; the sender gets ``error:<code>`` (an :class:`Error`)."""

    def __init__(self, code: int, message: str = "") -> None:
        self.code = Error(code)  # a number outside the table is a bug, found here
        super().__init__(f"error:{int(self.code)} {message}".strip())
        self.message = message


class SoftLimitError(CommandError):
    """A target lies outside the machine's travel: the line is refused and ALARM:2 raised."""

    def __init__(self, message: str) -> None:
        super().__init__(Error.SOFT_LIMIT, message)



class DrawingError(MotiondError):
    """A drawing (SVG, DXF, image) or its layer settings were refused by the import
    (:mod:`server.cam`): the message names what and where (an element, a line, a size)."""


class BackendFault(MotiondError):
    """The hardware below the backend failed in a way it can (a board shut down, a device
    gone): an alarm with its reason in one log line, not a bug's traceback."""
