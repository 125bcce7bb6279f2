"""Not a byte changed by the compiled encoders: a fixed job (the host benchmark's fast raster
with the laser following the pieces: queue_step, set_next_step_dir and reset_step_clock from
the compiled step axes, queue_pwm_out from a prepared encoder) sends exactly the bytes the
generic :meth:`Dictionary.encode` gives for what each message says, and the prepared
encoders change nothing when swapped for the generic one."""

from __future__ import annotations

from collections.abc import Callable

import pytest

from benchmarks import bench_klipper_host as bench
from server.backends.klipper.dictionary import Dictionary


class GenericDictionary(Dictionary):
    """Every prepared encoder replaced by the generic encoder, by parameter name."""

    def encoder(self, name: str) -> Callable[..., bytes]:
        names = [pname for pname, _, _ in self.by_name[name].params]
        return lambda *values: self.encode(name, **dict(zip(names, values, strict=True)))


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


def test_a_job_sends_the_bytes_of_the_generic_encoder(monkeypatch: pytest.MonkeyPatch) -> None:
    prepared, generic = sent(monkeypatch, False), sent(monkeypatch, True)
    assert len(prepared) > 500  # steps, direction changes and PWM all there
    d = bench.dictionary()
    decoded = [d.decode(m) for m in prepared]
    assert {"queue_step", "set_next_step_dir", "reset_step_clock", "queue_pwm_out"} <= {
        name for message in decoded for name, _ in message}
    assert [b"".join(d.encode(name, **params) for name, params in message)
            for message in decoded] == prepared
    assert prepared == generic
