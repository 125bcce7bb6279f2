"""The Klipper wire format, cross-checked byte for byte with Klipper's own host decoder."""

from __future__ import annotations

import random

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from klippy import msgproto  # type: ignore[import-untyped]

from server.backends.klipper.codec import (
    PAYLOAD_MAX,
    BlockReader,
    ProtocolError,
    crc16_ccitt,
    decode_vlq,
    encode_vlq,
    frame,
    vlq_size,
)
from server.backends.klipper.dictionary import Dictionary, vlq
from server.backends.klipper.outputs import level
from server.backends.klipper.stepcompress import StepCompressor, run_clocks
from server.backends.klipper.stepcore import StepAxis
from server.backends.klipper.steptimes import Spans, step_target
from tests.support.klipper_dictionary import compressed, dictionary_data


def reference(id_offset: int = 0) -> msgproto.MessageParser:
    parser = msgproto.MessageParser()
    parser.process_identify(compressed(dictionary_data(id_offset=id_offset)))
    return parser


@pytest.mark.parametrize("value", [0, 1, -1, -32, 95, 96, -33, 12287, -4096, 12288, -4097,
                                   1572863, -524288, 201326591, -67108864, 2**31 - 1, -2**31,
                                   2**32 - 1, 72_000_000])
def test_vlq_matches_klipper_for_every_size_boundary(value: int) -> None:
    ours = bytearray()
    encode_vlq(ours, value)
    theirs: list[int] = []
    msgproto.PT_uint32().encode(theirs, value)
    assert bytes(ours) == bytes(theirs) and len(ours) == vlq_size(value)
    signed = value - 2**32 if value >= 2**31 else value
    assert decode_vlq(bytes(ours), 0, signed=True) == (signed, len(ours))
    assert decode_vlq(bytes(ours), 0, signed=False) == (value & 0xFFFFFFFF, len(ours))


def test_crc16_matches_klipper_on_random_blocks() -> None:
    rng = random.Random(7)
    for _ in range(200):
        data = bytes(rng.randrange(256) for _ in range(rng.randrange(1, 62)))
        assert list(crc16_ccitt(data).to_bytes(2)) == msgproto.crc16_ccitt(data)


@given(st.binary(max_size=PAYLOAD_MAX), st.integers(0, 2**20))
def test_a_compiled_block_is_the_block_klippy_checks(payload: bytes, seq: int) -> None:
    """Framing and checksum are compiled: every payload size, every sequence number, the
    block klippy's own parser accepts, its crc klippy's (from the bytes, not the table)."""
    block = frame(seq, payload)
    head = bytes((len(payload) + 5, 0x10 | (seq & 0x0F))) + payload
    assert block == head + bytes(msgproto.crc16_ccitt(head)) + b"\x7e"
    assert reference().check_packet(bytearray(block)) == len(block)


def test_a_block_too_long_is_refused_before_the_compiled_framing() -> None:
    with pytest.raises(ProtocolError, match="exceeds"):
        frame(0, bytes(PAYLOAD_MAX + 1))


@pytest.mark.parametrize("id_offset", [0, 41])
def test_every_encoded_command_decodes_identically_with_klippy(id_offset: int) -> None:
    ours = Dictionary(dictionary_data(id_offset=id_offset))
    parser = reference(id_offset)
    commands = [
        ("queue_step", {"oid": 3, "interval": 7458, "count": 10, "add": -331}),
        ("queue_step", {"oid": 0, "interval": 2**32 - 5, "count": 65535, "add": 32767}),
        ("config_stepper", {"oid": 1, "step_pin": "PB13", "dir_pin": "PC2", "invert_step": 0,
                            "step_pulse_ticks": 144}),
        ("config_pwm_out", {"oid": 4, "pin": "PA8", "cycle_ticks": 7200, "value": 0,
                            "default_value": 0, "max_duration": 0}),
        ("reset_step_clock", {"oid": 2, "clock": 4_000_000_000}),
        ("finalize_config", {"crc": 0xDEADBEEF}),
        ("get_clock", {}),
    ]
    for seq, (name, params) in enumerate(commands):
        block = frame(seq, ours.encode(name, **params))
        assert parser.check_packet(bytearray(block)) == len(block)
        decoded = parser.parse(bytearray(block))
        assert decoded.pop("#name") == name
        assert decoded == params
        text = " ".join([name, *(f"{k}={v}" for k, v in params.items())])
        assert block[2:-3] == bytes(parser.create_command(text))


def test_responses_encoded_by_klippy_decode_with_our_dictionary() -> None:
    ours = Dictionary(dictionary_data())
    parser = reference()
    fmt = parser.lookup_command("config is_config=%c crc=%u is_shutdown=%c move_count=%hu")
    payload = bytes(fmt.encode([1, 0x12345678, 0, 512]))
    assert ours.decode(payload) == [
        ("config", {"is_config": 1, "crc": 0x12345678, "is_shutdown": 0, "move_count": 512})]
    fmt = parser.lookup_command("stepper_position oid=%c pos=%i")
    assert ours.decode(bytes(fmt.encode([2, -1234567])))[0][1] == {"oid": 2, "pos": -1234567}
    fmt = parser.lookup_command("shutdown clock=%u static_string_id=%hu")
    reason = ours.decode(bytes(fmt.encode([99, "Move queue overflow"])))[0][1]
    assert reason["static_string_id"] == "Move queue overflow"


def test_identify_response_carries_raw_bytes() -> None:
    boot = Dictionary.bootstrap()
    blob = compressed(dictionary_data())[:40]
    payload = bytearray()
    encode_vlq(payload, 0)
    encode_vlq(payload, 80)
    encode_vlq(payload, len(blob))
    payload += blob
    assert boot.decode(bytes(payload)) == [("identify_response", {"offset": 80, "data": blob})]
    assert boot.encode("identify", offset=40, count=40) == bytes([1, 40, 40])


def test_an_unknown_pin_names_the_pin() -> None:
    with pytest.raises(ProtocolError, match="PZ9"):
        Dictionary(dictionary_data()).encode(
            "config_stepper", oid=0, step_pin="PZ9", dir_pin="PA1", invert_step=0,
            step_pulse_ticks=0)


def test_the_block_reader_skips_corruption_and_resyncs() -> None:
    good = [frame(i, bytes([3, i])) for i in range(4)]
    corrupt = bytearray(good[1])
    corrupt[3] ^= 0x40
    reader = BlockReader()
    stream = b"\x7e\x00garbage" + good[0] + bytes(corrupt) + good[2] + good[3]
    blocks = []
    for i in range(0, len(stream), 3):  # arrives in pieces
        blocks += reader.feed(stream[i:i + 3])
    assert [b.seq for b in blocks] == [0, 2, 3]
    assert reader.bad_blocks >= 1


_HOT = ("queue_step", "set_next_step_dir", "reset_step_clock", "queue_digital_out",
        "queue_pwm_out")
_RANGES = {"%u": (0, 2**32 - 1), "%i": (-2**31, 2**31 - 1), "%hu": (0, 2**16 - 1),
           "%hi": (-2**15, 2**15 - 1), "%c": (0, 255)}


@given(data=st.data(), name=st.sampled_from(_HOT), id_offset=st.sampled_from([0, 41, 120]))
@settings(max_examples=300, deadline=None)
def test_prepared_encoders_give_the_generic_encoders_bytes(
        data: st.DataObject, name: str, id_offset: int) -> None:
    """The hot messages' prepared encoders (id and field order resolved once, VLQ by size)
    send exactly what the generic encoder and klippy's own msgproto send (ids of one byte
    and, with the offset of 120, of two)."""
    ours = Dictionary(dictionary_data(id_offset=id_offset))
    fmt = ours.by_name[name]
    params = {}
    for part in fmt.text.split()[1:]:
        pname, kind = part.split("=")
        params[pname] = data.draw(st.integers(*_RANGES[kind]), label=pname)
    prepared = ours.encoder(name)(*params.values())
    assert prepared == ours.encode(name, **params)
    if fmt.msgid < 96:  # klippy encodes one-byte message ids only
        text = " ".join([name, *(f"{k}={v}" for k, v in params.items())])
        assert prepared == bytes(reference(id_offset).create_command(text))


@given(st.integers(-2**31, 2**32 - 1))
def test_the_sized_vlq_matches_the_generic_one(value: int) -> None:
    generic = bytearray()
    encode_vlq(generic, value)
    assert vlq(value) == bytes(generic)


@given(st.lists(st.tuples(st.integers(0, 2**32 - 1), st.integers(1, 65535),
                          st.integers(-32768, 32767)), max_size=40),
       st.integers(0, 255), st.sampled_from([0, 41, 120]))
@settings(max_examples=200, deadline=None)
def test_compiled_queue_steps_are_the_generic_encoders_bytes(
        runs: list[tuple[int, int, int]], oid: int, id_offset: int) -> None:
    """A flush's runs as the compiled encoder sends them, byte for byte the generic
    (Python, by parameter name) encoder's, and decoded back to the same runs."""
    ours = Dictionary(dictionary_data(id_offset=id_offset))
    queue_step = ours.encoder("queue_step")
    compiled = b"".join(queue_step(oid, *run) for run in runs)
    generic = b"".join(ours.encode("queue_step", oid=oid, interval=interval, count=count,
                                   add=add) for interval, count, add in runs)
    assert compiled == generic
    assert ours.decode(compiled) == [
        ("queue_step", {"oid": oid, "interval": i, "count": c, "add": a}) for i, c, a in runs]


@given(st.floats(1.0, 200.0), st.floats(0.0, 3000.0), st.floats(0.005, 0.3),
       st.sampled_from([0.0, 0.01, 0.1]), st.integers(0, 255), st.booleans(),
       st.sampled_from([0, 41, 120]))
@settings(max_examples=200, deadline=None)
def test_a_step_axis_sends_the_compressed_runs_of_its_exact_steps_as_the_generic_encoder(
        v0: float, a: float, duration_s: float, back_s: float, oid: int, invert: bool,
        id_offset: int) -> None:
    """The compiled step axis (one call a sample to add, one to flush) sends what solving
    the spans, compressing each direction's steps from a reset a bound before the first
    (stepcompress.py, the state carried across a turn) and encoding each message with the
    generic encoder send: the same bytes, each run due (and its slot taken until) its first
    step's clock as the MCU counts it, a direction change due with its first step."""
    ours = Dictionary(dictionary_data(id_offset=id_offset))
    spans, per_mm, max_error = Spans(), 80.0, 400.0
    distance = v0 * duration_s + 0.5 * a * duration_s * duration_s
    target = step_target(0.3 + per_mm * distance)
    axis = StepAxis()
    axis.configure(oid, invert, max_error, *ours.step_prefixes())
    spans.add(0.3, per_mm, v0, a, duration_s, 0, target, 0.0)
    axis.span(0.3, per_mm, v0, a, duration_s, 0, target, 0.0)
    end = 0.3 + per_mm * distance
    back = step_target(end - per_mm * v0 * back_s)
    if back != target:  # a turn: the other way at v0
        spans.add(end, -per_mm, v0, 0.0, back_s, target, back, duration_s)
        axis.span(end, -per_mm, v0, 0.0, back_s, target, back, duration_s)
    to_clock = (1e6, 16e6, 0.0)
    assert axis.add(*to_clock) == spans.total
    sent: list[tuple[bytes, int | None, int]] = []
    axis.flush(0.0, True, sent, None)

    points, expected = spans.solve(to_clock), []
    if len(points):
        start = int(points[0] - max_error) - 1
        expected.append((ours.encode("reset_step_clock", oid=oid, clock=start), None, start))
        compressor, first = StepCompressor(max_error, start, float(start)), 0
        for row, count in zip(spans.rows, spans.counts, strict=True):
            if not count:
                continue
            run, first = points[first:first + count], first + count
            forward = row[6] > 0
            expected.append((ours.encode("set_next_step_dir", oid=oid, dir=int(forward != invert)),
                             None, int(run[0])))
            clock = compressor.last_clock
            runs, done = compressor.compress(run, final=True)
            assert done == len(run)
            for step_run in runs:
                due = int(run_clocks(clock, step_run)[0])
                expected.append((ours.encode("queue_step", oid=oid, interval=step_run.interval,
                                             count=step_run.count, add=step_run.add), due, due))
                clock = int(run_clocks(clock, step_run)[-1])
    assert sent == expected
    assert axis.held == 0 and axis.first_clock() is None


def test_a_prepared_encoder_refuses_another_count_of_parameters() -> None:
    with pytest.raises(TypeError, match="4 parameters, not 3"):
        Dictionary(dictionary_data()).encoder("queue_step")(0, 1, 2)


@given(st.one_of(st.floats(allow_nan=True), st.floats(-0.1, 1.1)),
       st.sampled_from([0, 1, 255, 256, 1023, 65535]))
def test_a_level_is_on_exactly_when_value_times_top_passes_one_half(value: float,
                                                                    top: int) -> None:
    """The followed output's quick on/off test (``value·top > 0.5``) agrees with the level
    the MCU is sent."""
    assert (level(value, top) > 0) == (value * (top or 1) > 0.5)
