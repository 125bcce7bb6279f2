"""Hostile requests on Klipper's API socket: each gets an error answer, changes nothing, logs
no traceback, and the same connection answers the next request.

Before (review of issue #36), each of these dropped the connection with a traceback, and
Moonraker then showed every front-end "Klippy disconnected": ``SET_VELOCITY_FACTOR
FACTOR=1e308`` (OverflowError), an id of ``NaN`` or ``1e999`` (the answer could not be
encoded), JSON nested 100,000 deep (RecursionError), a field list holding a list (unhashable);
a response template holding NaN broke every status push after it and alarmed the machine.
Scripts that set a negative feed factor or hold a line longer than every other input
accepts (256 characters: error 11) were taken.
motiond runs in this process with its real socket (tests/integration/test_klippy_api_socket).
"""

from __future__ import annotations

import asyncio
import json
import logging
from pathlib import Path

import pytest

from server.runtime.events import MachineState
from tests.integration.test_klippy_api_socket import served
from tests.support.klippy_client import ETX, klippy_client

DEEP = 100_000


def request(request_id: str, method: str, params: str = "{}") -> bytes:
    """A request written by hand (``request_id`` and ``params`` are raw JSON text)."""
    return f'{{"id": {request_id}, "method": "{method}", "params": {params}}}'.encode() + ETX


def script(text: str, request_id: int = 7) -> bytes:
    return request(str(request_id), "gcode/script", json.dumps({"script": text}))


HOSTILE: dict[str, tuple[bytes, object, str]] = {  # request, the answer's id, its message
    "an id of NaN": (request("NaN", "info"), None, "finite"),
    "an id of -Infinity": (request("-Infinity", "info"), None, "finite"),
    "an id of 1e999": (request("1e999", "info"), None, "finite"),
    "NaN in a response template": (
        request("7", "objects/subscribe",
                '{"objects": {"toolhead": null}, "response_template": {"x": NaN}}'), 7,
        "finite"),
    "JSON nested 100,000 deep in the params": (
        request("7", "info", '{"a": ' + "[" * DEEP + "]" * DEEP + "}"), 7, "nested"),
    "JSON nested 100,000 deep alone": (b"[" * DEEP + b"]" * DEEP + ETX, None, "nested"),
    "a field list holding a list": (
        request("7", "objects/query", '{"objects": {"toolhead": [["position"]]}}'), 7,
        "'objects'"),
    "a response template of 512 KiB": (
        request("7", "objects/subscribe", '{"objects": {"toolhead": null}, '
                '"response_template": {"a": "' + "x" * (1 << 19) + '"}}'),
        7, "response_template"),
    "a response template nested 900 deep": (
        request("7", "objects/subscribe", '{"objects": {"toolhead": null}, '
                '"response_template": {"a": ' + "[" * 900 + "]" * 900 + "}}"), 7,
        "response_template"),
    "SET_VELOCITY_FACTOR FACTOR=1e308": (script("SET_VELOCITY_FACTOR FACTOR=1e308"), 7,
                                         "FACTOR"),
    "SET_VELOCITY_FACTOR FACTOR=-1": (script("SET_VELOCITY_FACTOR FACTOR=-1"), 7, "FACTOR"),
    "a line of 100,000 characters": (script("M117 " + "x" * 100_000), 7, "error:11"),
}


@pytest.mark.parametrize("name", list(HOSTILE))
async def test_a_hostile_request_gets_an_error_and_the_connection_goes_on(
        name: str, tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    data, answer_id, reason = HOSTILE[name]
    caplog.set_level(logging.WARNING)
    async with served(tmp_path) as (app, socket), klippy_client(socket) as api:
        await api.raw(data)
        answer = await api.message()
        assert answer["id"] == answer_id and reason in answer["error"]["message"], answer
        await asyncio.sleep(0.3)  # a status push period: nothing was kept that breaks it
        assert (await api.call("info"))["result"]["state"] == "ready"
        status = await api.call("objects/query", objects={"gcode_move": ["speed_factor"]})
        assert status["result"]["status"]["gcode_move"]["speed_factor"] == 1.0
        assert app.kernel.state is MachineState.IDLE
    assert not [r for r in caplog.records if r.exc_info], "no traceback for an expected fault"
