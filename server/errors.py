"""The one exception tree of motiond.

Two kinds of error (STYLE.md habit 10): a :class:`CommandError` is answered to its sender as
``error:N`` and changes nothing; anything else unexpected alarms the machine.
"""

from __future__ import annotations


class MotiondError(Exception):
    """Base class of every error motiond raises on purpose."""


class ConfigError(MotiondError):
    """A configuration file is invalid. ``problems`` holds one readable line per problem."""

    def __init__(self, problems: list[str]) -> None:
        super().__init__("\n".join(problems))
        self.problems = problems


class CommandError(MotiondError):
    """A line or command was refused; the sender gets ``error:<code>``.

    Codes follow Grbl 1.1 (see PROTOCOL.md); codes above 38 are motiond's own, listed in
    :data:`MOTIOND_ERRORS`.
    """

    def __init__(self, code: int, message: str = "") -> None:
        super().__init__(f"error:{code} {message}".strip())
        self.code = code
        self.message = message


class SoftLimitError(CommandError):
    """A target lies outside the machine's travel: the line is refused and ALARM:2 raised."""

    def __init__(self, message: str) -> None:
        super().__init__(SOFT_LIMIT, message)


# motiond's own error numbers (Grbl leaves numbers above 38 free).
SOFT_LIMIT = 40
CHECKSUM = 41
LINE_NUMBER_SEQUENCE = 42
UNKNOWN_COMMAND = 43
FILE_ERROR = 44
BUSY = 45
AUTH_REQUIRED = 46

MOTIOND_ERRORS: dict[int, str] = {
    SOFT_LIMIT: "target outside the machine's travel (soft limit); ALARM:2 raised",
    CHECKSUM: "checksum mismatch; the line was not executed",
    LINE_NUMBER_SEQUENCE: "line number out of sequence",
    UNKNOWN_COMMAND: "unknown command",
    FILE_ERROR: "job file missing, unreadable or outside the data directory",
    BUSY: "refused while a job is running",
    AUTH_REQUIRED: "this connection may not control the machine",
}
