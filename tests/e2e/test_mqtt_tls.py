"""``mqtts://``: the module trusts the broker's certificate through ``ca_file``; with the wrong
CA it never connects, keeps retrying and leaves the machine alone (no alarm)."""

from __future__ import annotations

import asyncio
from pathlib import Path

import pytest

from server.app import App
from server.runtime.clock import RealClock
from server.runtime.events import MachineState
from tests.conftest import make_config
from tests.support.broker import mosquitto, self_signed, watching
from tests.support.helpers import running


def tls_config(url: str, ca_file: Path) -> dict[str, object]:
    return {"machine": {"name": "secure"}, "mqtt": {"url": url, "ca_file": str(ca_file)}}


async def connected(app: App) -> bool:
    module = app.kernel.modules["mqtt"]
    async with asyncio.timeout(10):
        while module.link is None or not module.link.connected:  # type: ignore[attr-defined]  # noqa: ASYNC110
            await asyncio.sleep(0.05)
    return True


async def test_mqtts_with_the_broker_ca_publishes(tmp_path: Path) -> None:
    async with mosquitto(tmp_path / "broker", tls=True) as broker:
        config = make_config(tls_config(broker.url, tmp_path / "broker" / "cert.pem"))
        async with running(config, RealClock()) as app:
            assert await connected(app)
            # the test's own client over TLS reads what the module published
            from ssl import create_default_context

            context = create_default_context(cafile=str(tmp_path / "broker" / "cert.pem"))
            async with watching(broker, "motiond/secure/availability",
                                tls_context=context) as watch:
                assert await watch.wait_for("motiond/secure/availability") == b"online"


@pytest.mark.parametrize("ca", ["another CA", "not a certificate"])
async def test_the_wrong_ca_never_connects_and_never_alarms_the_machine(
    tmp_path: Path, ca: str
) -> None:
    if ca == "another CA":
        await self_signed(tmp_path / "ca.pem", tmp_path / "ca-key.pem")
    else:
        (tmp_path / "ca.pem").write_text("-----BEGIN CERTIFICATE-----\nnonsense\n")
    async with mosquitto(tmp_path / "broker", tls=True) as broker:
        config = make_config(tls_config(broker.url, tmp_path / "ca.pem"))
        async with running(config, RealClock()) as app:
            await asyncio.sleep(2.0)  # several attempts (back-off from 0.5 s)
            module = app.kernel.modules["mqtt"]
            state = app.kernel.state
            link = module.link  # type: ignore[attr-defined]
    assert state is MachineState.IDLE, "a broker that cannot be trusted is not an alarm"
    assert link is not None and link.connections == 0
