"""Drawings over the JSON API: a real server on a real port, the import in its worker process,
the job it stores placed, previewed and run on the simulated machine."""

from __future__ import annotations

import asyncio
import base64
import io
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from server.api import drawing_worker
from server.runtime.clock import RealClock
from tests.support.api_client import api_config, client, serving

DATA = Path(__file__).parents[1] / "data" / "cam"


def _b64(data: bytes) -> str:
    return base64.b64encode(data).decode()


async def test_read_lists_the_layers_with_a_preview_of_their_shapes(tmp_path: Path) -> None:
    async with serving(api_config(tmp_path)) as (_, address), client(address) as rpc:
        drawing = await rpc.call("drawing.read", name="three-colours.svg",
                                 base64=_b64((DATA / "three-colours.svg").read_bytes()))
        layers = {layer["name"]: layer for layer in drawing["layers"]}
        assert [(name, layer["settings"]["mode"]) for name, layer in layers.items()] == [
            ("#0000ff", "fill"), ("#008000", "line"), ("#ff0000", "line")]
        assert (drawing["width_mm"], drawing["height_mm"]) == (120.0, 90.0)
        outline = max(layers["#ff0000"]["paths"], key=len)
        xs, ys = outline[0::2], outline[1::2]
        assert (min(xs), max(xs), min(ys), max(ys)) == pytest.approx((5, 115, 5, 85), abs=0.01)


async def test_generate_stores_a_job_that_places_previews_and_runs(tmp_path: Path) -> None:
    config = api_config(tmp_path)
    async with serving(config, RealClock()) as (app, address), client(address) as rpc:
        await rpc.call("machine.subscribe", topics=["job"])
        made = await rpc.call(
            "drawing.generate", name="settings.svg",
            base64=_b64((DATA / "settings.svg").read_bytes()),
            layers={"#000000": {"speed_mm_min": 12000, "power_pct": 40, "passes": 1}})
        assert made["job"]["name"] == "settings.gcode" and made["lines"] > 100
        progress = await rpc.wait_for("notify_drawing_progress",
                                      lambda p: p["fraction"] == 1.0 and p["task"] == "generate")
        assert progress["name"] == "settings.svg"
        assert "settings.gcode" in [f["name"] for f in await rpc.call("job.list")]
        place = await rpc.call("job.place", name="settings.gcode")
        assert place["fits"] and place["size_mm"]["X"] == pytest.approx(72.0, abs=0.5)
        path = await rpc.call("job.toolpath", name="settings.gcode")
        assert 1 in path["kinds"] and max(path["powers"]) == pytest.approx(40.0)
        job = await rpc.call("job.start", name="settings.gcode")
        assert job["state"] == "running"
        async with asyncio.timeout(30):
            while True:
                state = (await rpc.call("job.progress"))["state"]
                if state != "running":
                    break
                await asyncio.sleep(0.1)
        assert state == "done"


async def test_a_hostile_drawing_is_refused_and_the_server_keeps_answering(
        tmp_path: Path) -> None:
    laughs = (b'<?xml version="1.0"?>\n<!DOCTYPE svg [<!ENTITY a "aaaa">]>\n'
              b'<svg xmlns="http://www.w3.org/2000/svg"><desc>&a;</desc></svg>')
    async with serving(api_config(tmp_path)) as (_, address), client(address) as rpc:
        refused = await rpc.error("drawing.read", name="laughs.svg", base64=_b64(laughs))
        assert refused["code"] == 44 and "laughs.svg, line 2" in refused["message"]
        assert "entity declarations" in refused["message"]
        assert (await rpc.call("machine.status"))["state"] == "Idle"


async def test_an_import_over_its_time_or_memory_is_stopped(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    pixels = np.random.default_rng(1).integers(0, 255, (6000, 6000), dtype=np.uint8)
    buffer = io.BytesIO()
    Image.fromarray(pixels).save(buffer, "PNG", compress_level=1)
    path = tmp_path / "jobs" / "noise.png"
    path.parent.mkdir(exist_ok=True)
    path.write_bytes(buffer.getvalue())  # as POST /upload would have stored it
    async with serving(api_config(tmp_path)) as (_, address), client(address) as rpc:
        monkeypatch.setattr(drawing_worker, "MEMORY_BYTES", 400 << 20)
        refused = await rpc.error("drawing.generate", name="noise.png", file="noise.png",
                                  width_mm=600.0)
        assert "needs over 400 MB" in refused["message"]
        monkeypatch.setattr(drawing_worker, "MEMORY_BYTES", 2 << 30)
        monkeypatch.setattr(drawing_worker, "TIMEOUT_S", 0.2)
        refused = await rpc.error("drawing.read", name="noise.png", file="noise.png")
        assert "took over 0.2 s and was stopped" in refused["message"]
        assert (await rpc.call("machine.status"))["state"] == "Idle"


async def test_the_material_library_is_kept_in_the_data_folder(tmp_path: Path) -> None:
    async with serving(api_config(tmp_path)) as (_, address), client(address) as rpc:
        assert await rpc.call("material.list") == {}
        saved = await rpc.call("material.save", name="plywood",
                               layers={"#ff0000": {"speed_mm_min": 600, "passes": 2}})
        assert saved == {"plywood": {"#ff0000": {"speed_mm_min": 600.0, "passes": 2}}}
        refused = await rpc.error("material.save", name="acrylic",
                                  layers={"#ff0000": {"power_pct": 300}})
        assert refused["code"] == 44 and "power_pct" in refused["message"]
        assert '"plywood"' in (tmp_path / "materials.json").read_text()
        assert await rpc.call("material.list") == saved
        assert await rpc.call("material.delete", name="plywood") == {}
        assert (await rpc.error("material.delete", name="plywood"))["code"] == 44


async def test_a_large_import_never_stalls_the_event_loop(tmp_path: Path) -> None:
    from benchmarks.bench_import import large_svg

    path = tmp_path / "jobs" / "large.svg"
    path.parent.mkdir(exist_ok=True)
    path.write_bytes(large_svg(paths=400))  # 20,000 segments
    async with serving(api_config(tmp_path), RealClock()) as (app, address), \
            client(address) as rpc:
        monitor = app.kernel.loop_monitor
        await asyncio.sleep(0.2)
        monitor.reset()
        drawing = await rpc.call("drawing.read", name="large.svg", file="large.svg")
        points = sum(len(p) // 2 for layer in drawing["layers"] for p in layer["paths"])
        assert 5000 < points <= 6000 + 2 * 400  # each path keeps its ends
        made = await rpc.call("drawing.generate", name="large.svg", file="large.svg")
        assert made["lines"] > 100_000
        # the parsing ran in the worker; on the loop, only the replies' JSON (a few ms at most)
        assert monitor.worst_cpu_stall_s < 0.01, monitor.worst_cpu_stall_s
