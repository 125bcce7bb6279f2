"""The M-codes modules own, registered with the interpreter (pure: no asyncio, no I/O).

A module claims an M-code with a modal group and an *action factory*, as Klipper's
``register_command`` and mux commands do. The interpreter then reads a line once, whole:
``G1 X10 M106`` gives the move and the fan's action, in modal-group order (module codes run
after coolant, before dwell and motion), never a line routed away from the interpreter.

A factory is called while the line is interpreted, on the interpreter's copies: it must not
change anything itself, only return what the line should do (ordered :class:`Action` objects,
and :class:`Sync` requests such as ``message`` for a report). It may raise
:class:`~server.errors.CommandError` to refuse the line; the line then changes nothing.

A *mux* code (``M42 P<pin>``) is shared: each owner claims one value of a key word, and the
line goes to the owner of the value it names.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, replace

from server.errors import CommandError, Error
from server.gcode.modal import M_GROUPS, VALUE_LETTERS
from server.motion.moves import Output


@dataclass(frozen=True, slots=True)
class CodeCall:
    """One use of a module's M-code on a line.

    Attributes:
        code: the M number.
        values: the line's value words (F S T P L R I J K) as written, in program units.
        line_number: the line's N number, if any.
    """

    code: int
    values: Mapping[str, float]
    line_number: int | None


CodeFactory = Callable[[CodeCall], list[Output]]


@dataclass(frozen=True, slots=True)
class ModuleCode:
    """An M-code claimed by a module.

    Attributes:
        owner: the config section of the module (``switch.fan``), named in conflicts.
        code: the M number.
        group: modal group: two codes of one group on a line are error 21.
        factory: the line's value words -> what the code does.
        uses: the value letters it reads (so they are not "unused words", error 36).
        query: with no value words on the line, the code only reports (read-only connections
            and a locked machine may run it).
    """

    owner: str
    code: int
    group: str
    factory: CodeFactory
    uses: frozenset[str]
    query: bool


class CodeConflict(ValueError):
    """Two owners claim one code (or a module claims a core code): a config error."""


class CodeTable:
    """The module codes of one machine; shared by the live interpreter and offline runs."""

    def __init__(self) -> None:
        self._plain: dict[int, ModuleCode] = {}
        self._mux: dict[int, tuple[str, dict[str, ModuleCode]]] = {}

    def register(
        self,
        owner: str,
        code: int,
        factory: CodeFactory,
        *,
        group: str | None = None,
        uses: str = "",
        query: bool = False,
        key: tuple[str, str] | None = None,
    ) -> None:
        """Claim ``M<code>`` for ``owner``; ``key=("P", "5")`` claims only ``M<code> P5``.

        Raises:
            CodeConflict: the code belongs to the interpreter or to another owner.
        """
        if code in M_GROUPS:
            raise CodeConflict(f"M{code} belongs to the G-code interpreter ([{owner}])")
        if not set(uses) <= VALUE_LETTERS:
            raise ValueError(f"uses: only value letters {sorted(VALUE_LETTERS)}, not {uses!r}")
        spec = ModuleCode(owner, code, group or owner, factory, frozenset(uses), query)
        if key is None:
            self._claim_plain(spec)
        else:
            self._claim_mux(spec, key)

    def _claim_plain(self, spec: ModuleCode) -> None:
        other = self._plain.get(spec.code) or _any_owner(self._mux.get(spec.code))
        if other is not None:
            raise CodeConflict(
                f"M{spec.code} is claimed by both [{other.owner}] and [{spec.owner}]"
            )
        self._plain[spec.code] = spec

    def _claim_mux(self, spec: ModuleCode, key: tuple[str, str]) -> None:
        letter, value = key[0].upper(), key[1].upper()
        if spec.code in self._plain:
            other = self._plain[spec.code].owner
            raise CodeConflict(f"M{spec.code} is claimed by both [{other}] and [{spec.owner}]")
        mux_letter, owners = self._mux.setdefault(spec.code, (letter, {}))
        if mux_letter != letter:
            raise ValueError(f"M{spec.code} is keyed by {mux_letter}, not {letter}")
        if value in owners:
            other = owners[value].owner
            raise CodeConflict(
                f"M{spec.code} {letter}{value} is claimed by both [{other}] and [{spec.owner}]"
            )
        owners[value] = spec

    def __deepcopy__(self, memo: dict[int, object]) -> CodeTable:
        return self  # the machine's one table: a copied interpreter keeps reading it

    def stand_ins(self) -> CodeTable:
        """The same claims (groups, words, mux values), each read as doing nothing: what a
        plan made in another process reads a job's module codes with, the modules staying
        in the server. Their codes change no position and take no time of their own."""
        table = CodeTable()
        table._plain = {code: replace(spec, factory=_no_outputs)
                        for code, spec in self._plain.items()}
        table._mux = {code: (letter, {value: replace(spec, factory=_no_outputs)
                                      for value, spec in owners.items()})
                      for code, (letter, owners) in self._mux.items()}
        return table

    def owns(self, code: int) -> bool:
        """Whether a module claims ``M<code>`` (in any of its mux values)."""
        return code in self._plain or code in self._mux

    def group(self, code: int) -> str:
        """The modal group of a claimed code (mux codes: the code's own group)."""
        spec = self._plain.get(code)
        return spec.group if spec is not None else f"M{code}"

    def is_query(self, code: int) -> bool:
        """Whether ``M<code>`` with no value words only reports."""
        spec = self._plain.get(code)
        return spec is not None and spec.query

    def lookup(self, code: int, values: Mapping[str, float]) -> ModuleCode:
        """The owner of ``M<code>`` on a line with these value words.

        Raises:
            CommandError: 28 when a mux code lacks its key word, 2 when no owner has its value.
        """
        spec = self._plain.get(code)
        if spec is not None:
            return spec
        letter, owners = self._mux[code]
        value = values.get(letter)
        if value is None:
            raise CommandError(Error.VALUE_WORD_MISSING, f"M{code} needs a {letter} word")
        text = f"{value:g}"
        found = owners.get(text) or owners.get(f"{letter}{text}")
        if found is None:
            raise CommandError(
                Error.BAD_NUMBER_FORMAT, f"M{code}: nothing is configured for {letter}{text}"
            )
        return found

    def claims(self) -> list[str]:
        """``M106 [switch.fan]`` for every claim, for diagnostics."""
        rows = [f"M{c} [{s.owner}]" for c, s in sorted(self._plain.items())]
        for code, (letter, owners) in sorted(self._mux.items()):
            rows += [f"M{code} {letter}{v} [{s.owner}]" for v, s in sorted(owners.items())]
        return rows


def _no_outputs(call: CodeCall) -> list[Output]:
    return []


def _any_owner(mux: tuple[str, dict[str, ModuleCode]] | None) -> ModuleCode | None:
    return next(iter(mux[1].values()), None) if mux else None
