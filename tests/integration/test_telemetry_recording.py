"""Vehicle telemetry reaches the recording: agents publish batches, the recorder writes rows.

The batch format and the batcher are checked in-process (round trips, hypothesis); the path
agent -> bus -> manager -> recorder process -> MCAP with real `hilswarm run` processes.
"""

from __future__ import annotations

import signal
import threading
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
import zenoh
from hilswarm.agents import bus
from hilswarm.agents.registry import resolve_vehicle
from hilswarm.agents.telemetry import Telemetry, TelemetryBatcher
from hypothesis import given, settings
from hypothesis import strategies as st
from mcap.reader import make_reader
from swarm_harness import REPO, RunProcess, Spy, connect_spy, read_recording, wait_for

LEAD_FOLLOW = REPO / "graphs" / "lead_follow.toml"
AGENTS = ("leader", "f1", "f2")
RATE_HZ = 20.0  # graphs/lead_follow.toml


@pytest.fixture
def spies() -> Iterator[list[Spy]]:
    opened: list[Spy] = []
    yield opened
    for spy in opened:
        spy.close()


def vehicle_channels(agent: str) -> dict[str, tuple[str, ...]]:
    """The telemetry channels (name -> field names) of a lead_follow Frisbee bot."""
    vehicle = resolve_vehicle("frisbee")(name=agent, dt=1.0 / RATE_HZ)
    return {channel.name: channel.fields for channel in vehicle.telemetry}


# -- the batch format and the batcher ----------------------------------------------------------


def test_batch_round_trip_keeps_names_rows_and_nan() -> None:
    telemetry = Telemetry()
    duty = telemetry.add_channel("wheel_duty", ("left", "right"), initial_capacity=2)
    volts = telemetry.add_channel("battery", ("battery",))
    batcher = TelemetryBatcher(telemetry)
    for k in range(5):
        duty.append(k, 0.05 * k, [float(k), -float(k)])
    volts.append(0, 0.0, [np.nan])
    batch = batcher.take()
    payload = bus.encode_telemetry_batch(
        (bus.telemetry_channel_head(c.name, c.fields), a.k, a.t, a.values) for c, a in batch
    )
    decoded = {rows.channel: rows for rows in bus.decode_telemetry_batch(payload)}
    assert decoded["wheel_duty"].fields == ("left", "right")
    np.testing.assert_array_equal(decoded["wheel_duty"].k, np.arange(5))
    np.testing.assert_array_equal(decoded["wheel_duty"].values[:, 1], -np.arange(5.0))
    assert np.isnan(decoded["battery"].values[0, 0])
    assert batcher.take() == []  # nothing new
    duty.append(5, 0.25, [5.0, -5.0])
    (channel, arrays), *rest = batcher.take()
    assert channel.name == "wheel_duty" and not rest
    assert arrays.k.tolist() == [5]


def test_batcher_skips_channels_and_restarts_after_clear() -> None:
    telemetry = Telemetry()
    telemetry.add_channel("u", ("a",)).append(0, 0.0, [1.0])
    state = telemetry.add_channel("state", ("x",))
    state.append(0, 0.0, [1.0])
    batcher = TelemetryBatcher(telemetry, skip=("u",))
    assert batcher.pending == 1
    assert [c.name for c, _ in batcher.take()] == ["state"]
    state.clear()
    state.append(7, 0.7, [2.0])
    (_, arrays), *_ = batcher.take()
    assert arrays.k.tolist() == [7]


@pytest.mark.parametrize(
    "payload",
    [b"", b"\x02\x00\x00", b"\x01\x01\x00\x03abc\x01\x01x\x05\x00\x00\x00", b"\x01\x00\x00\xff"],
)
def test_bad_batches_are_refused(payload: bytes) -> None:
    with pytest.raises(bus.BusMessageError):
        bus.decode_telemetry_batch(payload)


@settings(max_examples=50, deadline=None)
@given(
    n_fields=st.integers(1, 4),
    rows=st.integers(0, 30),
    seed=st.integers(0, 2**32 - 1),
)
def test_batch_round_trip_property(n_fields: int, rows: int, seed: int) -> None:
    rng = np.random.default_rng(seed)
    k = rng.integers(-(2**40), 2**40, rows)
    t = rng.normal(size=rows)
    values = rng.normal(size=(rows, n_fields))
    fields = tuple(f"f{i}" for i in range(n_fields))
    payload = bus.encode_telemetry_batch([(bus.telemetry_channel_head("c", fields), k, t, values)])
    decoded = bus.decode_telemetry_batch(payload)
    if rows == 0:
        assert decoded == []
        return
    (only,) = decoded
    assert only.fields == fields
    np.testing.assert_array_equal(only.k, k)
    np.testing.assert_array_equal(only.t, t)
    np.testing.assert_array_equal(only.values, values)


# -- real runs ---------------------------------------------------------------------------------


def start(runs: list[RunProcess], tmp_path: Path, *args: str) -> RunProcess:
    run = RunProcess(tmp_path, LEAD_FOLLOW, "--no-check", *args)
    runs.append(run)
    return run


def check_telemetry_topics(recording: dict, agent: str, *, slack: int) -> None:
    """Every channel of ``agent``'s vehicle is recorded, row for row with its ``y``."""
    ys = [m["k"] for m in recording[f"/{agent}/y"]]
    assert ys, f"/{agent}/y is empty"
    for channel, fields in vehicle_channels(agent).items():
        topic = f"/{agent}/telemetry/{channel}"
        messages = recording.get(topic, [])
        ks = [m["k"] for m in messages]
        assert ks == sorted(set(ks)), f"{topic}: rows repeat or are out of order"
        assert 0 <= len(ys) - len(ks) <= slack, (topic, len(ks), len(ys))
        assert set(ks) <= set(ys)
        for message in messages:
            assert list(message) == ["k", "t", "wall_ns", "values", *fields], message
            assert message["values"] == [message[f] for f in fields]
            assert message["t"] == pytest.approx(message["k"] / RATE_HZ)


@pytest.mark.integration
def test_lead_follow_records_every_telemetry_row(tmp_path: Path, runs: list[RunProcess]) -> None:
    run = start(runs, tmp_path, "--duration", "5")
    assert run.wait(120) == 0, run.output()
    recording = read_recording(run.out)
    assert len(recording["/leader/y"]) == 100
    for agent in AGENTS:
        check_telemetry_topics(recording, agent, slack=0)
    assert vehicle_channels("leader") == {
        "battery": ("battery",),
        "wheel_duty": ("left", "right"),
    }


class BatchSpy:
    """Collects the leader's telemetry batches as published (decoded), on a spy's session."""

    def __init__(self, spy: Spy) -> None:
        self._lock = threading.Lock()
        self.batches: list[list[bus.TelemetryRows]] = []
        self.subscriber = spy.session.declare_subscriber(
            spy.keys.telemetry_batches("leader"),
            zenoh.handlers.Callback(self._on_sample, indirect=False),
        )

    def _on_sample(self, sample: zenoh.Sample) -> None:
        rows = bus.decode_telemetry_batch(sample.payload.to_bytes())
        with self._lock:
            self.batches.append(rows)

    def snapshot(self) -> list[list[bus.TelemetryRows]]:
        with self._lock:
            return list(self.batches)


@pytest.mark.integration
def test_interrupted_run_keeps_every_batch_published_before_the_interrupt(
    tmp_path: Path, runs: list[RunProcess], spies: list[Spy]
) -> None:
    run = start(runs, tmp_path, "--mode", "realtime", "--duration", "60")
    spy = connect_spy(run, "lead_follow")
    spies.append(spy)
    batch_spy = BatchSpy(spy)
    run.remember_agents(3)
    wait_for(lambda: len(batch_spy.snapshot()) >= 4, 60, "4 telemetry batches of the leader")
    before = batch_spy.snapshot()
    run.process.send_signal(signal.SIGINT)
    assert run.wait(30) == 130, run.output()
    with run.out.open("rb") as f:
        assert make_reader(f).get_summary() is not None, "the MCAP file must be closed properly"
    recording = read_recording(run.out)
    largest_batch = max(len(rows.k) for batch in before for rows in batch)
    for agent in AGENTS:
        check_telemetry_topics(recording, agent, slack=largest_batch)
    for channel in ("battery", "wheel_duty"):
        recorded = {m["k"]: m["values"] for m in recording[f"/leader/telemetry/{channel}"]}
        published = [rows for batch in before for rows in batch if rows.channel == channel]
        assert published, f"no {channel} rows published before the interrupt"
        for rows in published:
            for k, values in zip(rows.k.tolist(), rows.values.tolist(), strict=True):
                assert recorded.get(k) == values, (channel, k)
