"""Not a byte changed by the prepared (compiled) encoders: a fixed job (the host benchmark's
fast raster with the laser following the pieces: queue_step, a flush's at once,
set_next_step_dir, reset_step_clock and queue_pwm_out) sends exactly the bytes it sends when
every message goes through the generic :meth:`Dictionary.encode` (computed both ways, nothing
recorded)."""

from __future__ import annotations

from collections.abc import Callable

import pytest

from benchmarks import bench_klipper_host as bench
from server.backends.klipper.dictionary import Dictionary, StepEncoder


class GenericDictionary(Dictionary):
    """Every prepared encoder replaced by the generic encoder, by parameter name."""

    def encoder(self, name: str) -> Callable[..., bytes]:
        names = [pname for pname, _, _ in self.by_name[name].params]
        return lambda *values: self.encode(name, **dict(zip(names, values, strict=True)))

    def step_encoder(self) -> StepEncoder:
        """A flush's runs one message at a time, each due at its first step."""
        def encode(oid: int, runs: list[tuple[int, int, int]],
                   last: int) -> tuple[list[tuple[bytes, int, int]], int]:
            messages = []
            for interval, count, add in runs:
                first = last + interval
                messages.append((self.encode("queue_step", oid=oid, interval=interval,
                                             count=count, add=add), first, first))
                last += count * interval + add * (count * (count - 1) // 2)
            return messages, last
        return encode


def sent(monkeypatch: pytest.MonkeyPatch, generic: bool) -> list[bytes]:
    messages: list[bytes] = []
    count = bench.WireCount.send

    def send(self: bench.WireCount, *burst: bytes) -> None:
        messages.extend(burst)
        count(self, *burst)

    with monkeypatch.context() as patch:
        patch.setattr(bench.WireCount, "send", send)
        if generic:
            data = bench.dictionary().data
            patch.setattr(bench, "dictionary", lambda: GenericDictionary(data))
        bench.execute(0.4)
    return messages


def test_a_job_sends_the_same_bytes_through_prepared_and_generic_encoders(
        monkeypatch: pytest.MonkeyPatch) -> None:
    prepared, generic = sent(monkeypatch, False), sent(monkeypatch, True)
    assert len(prepared) > 500  # steps, direction changes and PWM all there
    names = {bench.dictionary().decode(m)[0][0] for m in prepared}
    assert {"queue_step", "set_next_step_dir", "reset_step_clock", "queue_pwm_out"} <= names
    assert prepared == generic
