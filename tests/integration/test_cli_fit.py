"""``motiond estimate`` and ``render`` on real files: a time whatever the placement, the fit
from ``--origin`` reported apart, ``--require-fit`` for scripts, ``--config`` before or after
the command; ``$x=`` saves only what was changed."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest

from server.cli import main
from server.config_loader import load_config
from tests.conftest import CORPUS, REPO
from tests.support.helpers import running, submit_all

# The files a laser or a mill can run; the others stop at a line the machine refuses (G42
# cutter compensation, an arc off its circle, a 3D printer's M107), and say so.
VALID = ("laser-raster-tree.nc", "laser-vector-jsdc.gcode", "laser-engrave-tball.gcode",
         "cnc-arcs-arrows.nc")


def default_config(tmp_path: Path, **travel: float) -> Path:
    """The embedded default machine with its data directory in ``tmp_path`` (never the
    user's), optionally with another X/Y travel."""
    text = (REPO / "server" / "default.toml").read_text()
    for axis, max_mm in travel.items():
        text = text.replace(f"[axes.{axis}]\n", f"[axes.{axis}]\nmax_mm = {max_mm}\n", 1)
        text = text.replace(f"max_mm = {400 if axis == 'x' else 300}\n", "", 1)
    path = tmp_path / "machine.toml"
    path.write_text(text + f"\n[jobs]\ndata_dir = '{tmp_path}'\n")
    return path


def estimate_json(capsys: Any, *args: str) -> tuple[int, dict[str, Any]]:
    status = main([*args, "--json", "--no-progress"]) if "estimate" in args else main(list(args))
    return status, json.loads(capsys.readouterr().out)


@pytest.mark.parametrize("path", sorted(p for p in CORPUS.iterdir()
                                        if p.suffix in (".nc", ".gcode")), ids=lambda p: p.name)
def test_every_corpus_file_gets_a_time_and_a_fit(path: Path, tmp_path: Path, capsys: Any) -> None:
    config = default_config(tmp_path)
    status, result = estimate_json(capsys, "estimate", str(path), "--config", str(config))
    fit = result["fit"]
    assert set(fit) >= {"fits", "size_mm", "extent_min_mm", "misfits", "message"}
    if path.name in VALID:
        assert status == 0 and result["error"] is None
        assert result["duration_s"] > 60, "real jobs take minutes, never 0.00s"
        assert result["lines"] == len(path.read_text(errors="replace").splitlines())
    else:
        assert status == 1 and result["error"] and result["error_line"] > 1


def test_origin_changes_the_fit_and_require_fit_fails_a_misfit(
    tmp_path: Path, capsys: Any
) -> None:
    config = str(default_config(tmp_path))
    job = str(CORPUS / "laser-vector-jsdc.gcode")  # Y from -58.1 to 0: origin top-left
    status, at_zero = estimate_json(capsys, "estimate", job, "--config", config, "--require-fit")
    assert status == 3 and not at_zero["fit"]["fits"]
    (misfit,) = at_zero["fit"]["misfits"]
    assert misfit["axis"] == "Y" and misfit["below_mm"] == pytest.approx(58.115, abs=1e-3)
    assert misfit["origin_low_mm"] == pytest.approx(58.115, abs=1e-3)
    status, placed = estimate_json(capsys, "estimate", job, "--config", config,
                                   "--origin", "20,200", "--require-fit")
    assert status == 0 and placed["fit"]["fits"]
    assert placed["fit"]["extent_min_mm"]["Y"] == pytest.approx(200 - 58.115, abs=1e-3)
    assert placed["duration_s"] == pytest.approx(at_zero["duration_s"], rel=0.01), \
        "the time does not depend on the placement (the first rapid aside)"
    assert main(["estimate", job, "--config", config, "--no-progress"]) == 0, \
        "without --require-fit a misfit is reported, not an error"
    assert "fits        NO: Y: 58.115 mm below" in capsys.readouterr().out


def test_config_counts_before_and_after_the_command(tmp_path: Path, capsys: Any) -> None:
    small = str(default_config(tmp_path, x=50))
    job = str(CORPUS / "laser-raster-tree.nc")  # 100 mm wide: fits 400, not 50
    for args in (["--config", small, "estimate", job], ["estimate", job, "--config", small]):
        status, result = estimate_json(capsys, *args, "--require-fit")
        assert status == 3, args
        assert [m["axis"] for m in result["fit"]["misfits"]] == ["X"], args


def test_render_draws_every_line_and_reports_the_fit(tmp_path: Path, capsys: Any) -> None:
    config = str(default_config(tmp_path))
    out = tmp_path / "tball.svg"
    job = str(CORPUS / "laser-engrave-tball.gcode")
    assert main(["render", job, "-o", str(out), "--config", config,
                 "--origin", "10,200"]) == 0
    printed = capsys.readouterr()
    assert "fits        yes" in printed.out and "stopped" not in printed.err
    assert "(stopped at line" not in out.read_text()
    grey = tmp_path / "tball-power.svg"
    assert main(["render", job, "-o", str(grey), "--config", config, "--power"]) == 0
    assert "laser power (S / highest S)" in grey.read_text()


async def test_only_changed_settings_are_saved(tmp_path: Path) -> None:
    config_file = default_config(tmp_path)
    saved = tmp_path / "settings.toml"
    async with running(load_config(config_file)) as app:
        await submit_all(app, ["$120=900", "$20=0"])
        saved = app.kernel.machine.settings.path or saved
        assert saved.read_text().splitlines()[2:] == ['"20" = 0.0', '"120" = 900.0']
        await submit_all(app, ["$20=1"])  # back to the config's value: no longer saved
        assert saved.read_text().splitlines()[2:] == ['"120" = 900.0']
    config_file.write_text(config_file.read_text().replace("soft_limits = true",
                                                           "soft_limits = false"))
    async with running(load_config(config_file)) as app:
        core = app.kernel.config.core
        assert not core.machine.soft_limits, "the config's new default is not undone"
        assert core.axes["x"].accel_mm_s2 == 900.0
