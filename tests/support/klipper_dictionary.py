"""A data dictionary in the format of Klipper's MCU firmware, for the virtual MCU and tests.

The message formats are those of Klipper's stock firmware (src/*.c), and only the commands the
stock firmware's own dictionary (the klipper-avr rig's ``klipper.dict``) has: a command stock
firmware lacks (``config_reset``: Linux and PRU builds only) fails in the fast tests too. Ids
can be shifted by ``id_offset`` so tests prove the host never assumes an id beyond identify (1)
and identify_response (0).
"""

from __future__ import annotations

import json
import zlib
from typing import Any

from tests.support.rigs import stock_dictionary

COMMANDS = [
    "get_uptime",
    "get_clock",
    "get_config",
    "allocate_oids count=%c",
    "finalize_config crc=%u",
    "emergency_stop",
    "clear_shutdown",
    "reset",
    "config_stepper oid=%c step_pin=%c dir_pin=%c invert_step=%c step_pulse_ticks=%u",
    "queue_step oid=%c interval=%u count=%hu add=%hi",
    "set_next_step_dir oid=%c dir=%c",
    "reset_step_clock oid=%c clock=%u",
    "stepper_get_position oid=%c",
    "config_digital_out oid=%c pin=%u value=%c default_value=%c max_duration=%u",
    "queue_digital_out oid=%c clock=%u on_ticks=%u",
    "update_digital_out oid=%c value=%c",
    "config_pwm_out oid=%c pin=%u cycle_ticks=%u value=%hu default_value=%hu max_duration=%u",
    "queue_pwm_out oid=%c clock=%u value=%hu",
]
STOCK = stock_dictionary()
if STOCK is not None:
    COMMANDS = [text for text in COMMANDS if text in STOCK["commands"]]
RESPONSES = [
    "uptime high=%u clock=%u",
    "clock clock=%u",
    "config is_config=%c crc=%u is_shutdown=%c move_count=%hu",
    "shutdown clock=%u static_string_id=%hu",
    "is_shutdown static_string_id=%hu",
    "stepper_position oid=%c pos=%i",
    "stats count=%u sum=%u sumsq=%u",
    "starting",
]
SHUTDOWN_REASONS = ["Command request", "Move queue overflow", "Stepper too far in past",
                    "Can't reset time when stepper active", "Scheduled output in the past",
                    "Invalid oid type", "Rescheduled timer in the past",
                    "Missed scheduling of next hard pwm event",
                    "Missed scheduling of next digital out event",
                    "Scheduled pwm event will exceed max_duration",
                    "Shutdown cleared when not shutdown"]


def dictionary_data(
    clock_hz: int = 72_000_000, id_offset: int = 0, move_count: int = 512
) -> dict[str, Any]:
    """The JSON document an STM32F103 build of Klipper would serve (a subset)."""
    ids = iter(range(2 + id_offset, 200))
    commands = {"identify offset=%u count=%c": 1} | {text: next(ids) for text in COMMANDS}
    responses = {"identify_response offset=%u data=%.*s": 0} | {
        text: next(ids) for text in RESPONSES}
    return {
        "version": "v0.12.0-virtual",
        "build_versions": "motiond virtual MCU",
        "commands": commands,
        "responses": responses,
        "output": {},
        "enumerations": {
            "pin": {"PA0": [0, 16], "PB0": [16, 16], "PC0": [32, 16]},
            "static_string_id": {text: i + 1 for i, text in enumerate(SHUTDOWN_REASONS)},
        },
        "config": {"CLOCK_FREQ": clock_hz, "MCU": "stm32f103xe", "SERIAL_BAUD": 250000,
                   "PWM_MAX": 255, "RECEIVE_WINDOW": 192, "STATS_SUMSQ_BASE": 256,
                   "MOVE_COUNT": move_count},
    }


def compressed(data: dict[str, Any]) -> bytes:
    return zlib.compress(json.dumps(data).encode())
