"""The folder tree is the data flow: the pure cores import no I/O and nothing downstream."""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import pytest

SERVER = Path(__file__).resolve().parents[2] / "server"
PURE = ("gcode", "motion", "protocol")
# What a pure package may import from motiond: the other pure cores, the error table and the
# backend interface (a typing.Protocol), never the runtime, transports, API or offline tools.
ALLOWED = ("server.gcode", "server.motion", "server.protocol", "server.errors",
           "server.motion.backend")
FORBIDDEN_LIBRARIES = {"asyncio", "socket", "selectors", "threading", "subprocess",
                       "aiohttp", "websockets", "serial", "serial_asyncio"}


def imports(path: Path) -> set[str]:
    return imports_in(ast.parse(path.read_text()))


def imports_in(tree: ast.AST) -> set[str]:
    names: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names |= {alias.name for alias in node.names}
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names.add(node.module)
            if node.module == "server":
                names |= {f"server.{alias.name}" for alias in node.names}
    return names


def pure_files() -> list[Path]:
    return sorted(p for package in PURE for p in (SERVER / package).rglob("*.py"))


def test_the_pure_packages_exist() -> None:
    assert len(pure_files()) >= 10


@pytest.mark.parametrize("path", pure_files(), ids=lambda p: f"{p.parent.name}/{p.name}")
def test_a_pure_core_imports_no_io_and_nothing_downstream(path: Path) -> None:
    found = imports(path)
    libraries = {name.split(".")[0] for name in found} & FORBIDDEN_LIBRARIES
    assert not libraries, f"{path.name} imports I/O: {sorted(libraries)}"
    ours = {name for name in found if name == "server" or name.startswith("server.")}
    downstream = {name for name in ours if not name.startswith(ALLOWED)}
    assert not downstream, f"{path.name} imports {sorted(downstream)}"


def test_the_folders_are_layers_with_no_import_circle_between_them() -> None:
    """import-linter's contracts in pyproject.toml: each folder imports only the layers below
    it (``if TYPE_CHECKING:`` imports count too), and the pure cores no I/O library."""
    lint = "from importlinter.cli import lint_imports_command; lint_imports_command()"
    done = subprocess.run([sys.executable, "-c", lint], cwd=SERVER.parent,
                          capture_output=True, text=True, timeout=120, check=False)
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-2000:]
    assert "Contracts: 2 kept, 0 broken." in done.stdout


def test_no_source_file_is_over_500_lines() -> None:
    packages = [SERVER, SERVER.parent / "modules"]
    long = {str(p.relative_to(SERVER.parent)): n for package in packages
            for p in package.rglob("*.py") if (n := len(p.read_text().splitlines())) > 500}
    assert not long, f"split these along a seam they already have: {long}"


def test_the_runtime_holds_at_most_a_dozen_files() -> None:
    assert len(list((SERVER / "runtime").glob("*.py"))) <= 12


def test_the_line_protocol_points_one_way_events_scanner_lines() -> None:
    """The events know no protocol code; the byte scanner knows the events, no line meaning."""
    protocol = SERVER / "protocol"
    ours = {n for n in imports(protocol / "events.py") if n.startswith("server.protocol")}
    assert not ours, f"protocol/events.py imports {sorted(ours)}"
    ours = {n for n in imports(protocol / "scanner.py") if n.startswith("server.protocol")}
    assert ours == {"server.protocol.events"}, f"protocol/scanner.py imports {sorted(ours)}"


def test_only_the_cli_imports_the_estimate_and_render_commands() -> None:
    """The offline pipeline and the server never depend on the command-line front end."""
    for path in sorted(SERVER.rglob("*.py")):
        if path.parent.name == "cli":
            continue
        assert "server.cli.offline" not in imports(path), f"{path.name} imports the CLI"


def test_the_config_models_read_no_file() -> None:
    found = imports(SERVER / "config.py") & {"tomllib", "importlib", "server.config_loader"}
    assert not found, f"config.py imports {sorted(found)}: loading is config_loader.py"


# A class split into parts along a seam: the parts are base classes of the whole, on its state.
PARTS = {
    "server.machine.machine": ("server.machine.feed", "server.machine.controls"),
    "server.sessions.session": ("server.sessions.input", "server.sessions.output"),
}


def runtime_imports(path: Path) -> set[str]:
    """What a module imports when it runs: :func:`imports` without ``if TYPE_CHECKING:``."""
    tree = ast.parse(path.read_text())
    for node in ast.walk(tree):
        if isinstance(node, ast.If) and getattr(node.test, "id", "") == "TYPE_CHECKING":
            node.body = []
    return imports_in(tree)


def module_name(path: Path) -> str:
    return ".".join(path.relative_to(SERVER.parent).with_suffix("").parts)


def test_the_parts_of_a_split_class_import_their_whole_only_for_type_checking() -> None:
    for whole, parts in PARTS.items():
        for part in parts:
            path = SERVER.parent / (part.replace(".", "/") + ".py")
            assert whole not in runtime_imports(path), f"{part} imports {whole} at run time"


def test_only_the_whole_and_its_parts_import_a_part() -> None:
    packages = [SERVER, SERVER.parent / "modules"]
    for path in sorted(p for package in packages for p in package.rglob("*.py")):
        name = module_name(path)
        for whole, parts in PARTS.items():
            if name == whole or name in parts:
                continue
            used = imports(path) & set(parts)
            assert not used, f"{name} imports {sorted(used)}: use {whole}"
