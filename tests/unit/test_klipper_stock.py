"""The stock Klipper firmware's own dictionary (the klipper-avr rig's ``klipper.dict``, with
message ids of two bytes and negative ones) encodes and decodes as its own ``msgproto.py``
does; the virtual MCU of the fast tests offers nothing the stock firmware lacks."""

from __future__ import annotations

import json

import pytest

from server.backends.klipper.codec import ProtocolError, frame
from server.backends.klipper.dictionary import Dictionary
from tests.support.klipper_dictionary import dictionary_data
from tests.support.rigs import msgproto, rig


def stock() -> tuple[Dictionary, object]:
    data = (rig("klipper-avr") / "klipper.dict").read_bytes()
    parser = msgproto().MessageParser()
    parser.process_identify(data, decompress=False)
    return Dictionary(json.loads(data)), parser


def test_the_virtual_mcu_offers_only_the_commands_the_stock_firmware_has() -> None:
    data = json.loads((rig("klipper-avr") / "klipper.dict").read_bytes())
    virtual = dictionary_data()
    assert set(virtual["commands"]) <= set(data["commands"])
    assert {"emergency_stop", "clear_shutdown", "reset"} <= {
        text.split()[0] for text in virtual["commands"]}
    with pytest.raises(ProtocolError, match="config_reset"):
        Dictionary(virtual).encode("config_reset")  # Linux and PRU builds only


def test_commands_encode_byte_for_byte_as_the_firmware_s_own_msgproto() -> None:
    ours, parser = stock()
    commands = [
        ("emergency_stop", {}), ("clear_shutdown", {}), ("reset", {}),  # ids 3, 2, -16
        ("stepper_get_position", {"oid": 1}),
        ("queue_step", {"oid": 0, "interval": 2**32 - 5, "count": 65535, "add": -32768}),
        ("config_pwm_out", {"oid": 4, "pin": "PB4", "cycle_ticks": 2000, "value": 0,
                            "default_value": 0, "max_duration": 20_000_000}),
        ("config_digital_out", {"oid": 5, "pin": "PA2", "value": 1, "default_value": 1,
                                "max_duration": 0}),
    ]
    for seq, (name, params) in enumerate(commands):
        block = frame(seq, ours.encode(name, **params))
        assert parser.check_packet(bytearray(block)) == len(block)  # type: ignore[attr-defined]
        text = " ".join([name, *(f"{k}={v}" for k, v in params.items())])
        assert block[2:-3] == bytes(parser.create_command(text))  # type: ignore[attr-defined]


@pytest.mark.parametrize(("text", "values", "expected"), [
    ("starting", [], {}),  # -15
    ("shutdown clock=%u static_string_id=%hu", [123456, "Command request"],
     {"clock": 123456, "static_string_id": "Command request"}),  # -13
    ("stepper_position oid=%c pos=%i", [0, -2106], {"oid": 0, "pos": -2106}),  # -6
    ("neopixel_result oid=%c success=%c", [3, 1], {"oid": 3, "success": 1}),  # 130
])
def test_responses_of_every_id_width_decode_as_the_firmware_sent_them(
    text: str, values: list[object], expected: dict[str, object]
) -> None:
    ours, parser = stock()
    payload = bytes(parser.lookup_command(text).encode(values))  # type: ignore[attr-defined]
    assert ours.decode(payload) == [(text.split()[0], expected)]
