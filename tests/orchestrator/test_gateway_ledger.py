"""The gateway stage of the latency ledger on the recorder's side (tick report -> the ticks of
``/orchestrator/ticks`` -> ``plot --latency``), and the STALE counter in the run's outcome."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from hilswarm.agents import bus
from hilswarm.agents.mcap_io import iter_messages
from hilswarm.orchestrator import plotting
from hilswarm.orchestrator.experiment import load_experiment
from hilswarm.orchestrator.outcome import CLEAN, DEGRADED, decide
from hilswarm.orchestrator.record_stream import RecordWriter
from hilswarm.orchestrator.recorder import Recorder, record_vehicles
from hilswarm.orchestrator.run_summary import RunSummary
from hilswarm.orchestrator.stream_recorder import StreamRecorder

GRAPHS = Path(__file__).resolve().parents[2] / "graphs"
T0 = 1_800_000_000_000_000_000  # a log time [ns, Unix epoch]
ANSWER_S = 0.02
LINK_S = 0.015
GATEWAY_S = 0.001
RADIO_S = 0.012


def _report(i: int, k: int) -> bytes:
    """Agent 0 on a plain link, agent 1 through the gateway (NaN stages at tick 3: its
    exchange had no answer), agent 2 through the gateway without u and x_hat."""
    timing = bus.AgentTiming(compute_s=1e-4, actuate_s=2e-4, sense_s=3e-4, link_s=LINK_S)
    if i == 1:
        stages = (math.nan, math.nan) if k == 3 else (GATEWAY_S, RADIO_S)
        timing = bus.AgentTiming(1e-4, 2e-4, 3e-4, 0, LINK_S, 1, *stages)
        return bus.encode_report(timing, np.array([0.5, -0.5]), np.array([1.0, 2.0, 3.0]))
    if i == 2:
        timing = bus.AgentTiming(1e-4, 2e-4, 3e-4, 0, LINK_S, 0, GATEWAY_S, 0.0)
        return bus.encode_report(timing, None, None)
    return bus.encode_report(timing, np.array([0.1, 0.2]), np.array([3.0]))


@pytest.fixture
def ticks(tmp_path: Path) -> list[dict]:
    """The /orchestrator/ticks of 6 ticks of three agents, through the stream recorder."""
    experiment = load_experiment(GRAPHS / "lead_follow.toml", overrides={"duration_s": 1.0})
    path = tmp_path / "ledger.mcap"
    writer = RecordWriter(experiment.agent_names)
    for k in range(6):
        for i in range(3):
            payload = bus.encode_vector(k, k * experiment.dt, [float(i), 0.0, 0.0])
            writer.y(i, T0 + k, payload, _report(i, k))
        writer.tick(
            k, T0 + k, scheduled_s=k * experiment.dt, send_delay_s=1e-5, completion_s=ANSWER_S,
            late=[], missing=[], answer_s=np.full(3, ANSWER_S),
        )  # fmt: skip
    with Recorder(path, experiment, log_time_ns=T0) as recorder:
        record_vehicles(recorder, experiment, log_time_ns=T0)
        stream = StreamRecorder(recorder, experiment)
        # from tick 1 on, each agent's y messages take the layout cached for their length
        stream.write(writer.close(T0).data)
        assert stream.errors == 0
    messages = [m for topic, _, m in iter_messages(path) if topic == "/orchestrator/ticks"]
    assert len(messages) == 6
    return messages


def test_the_gateway_stages_are_in_the_ledger_of_agents_through_the_gateway(
    ticks: list[dict],
) -> None:
    plain, gateway, no_signals = (ticks[4]["agents"][name] for name in ("leader", "f1", "f2"))
    assert plain == {
        "answer_s": ANSWER_S, "bus_s": ANSWER_S - (1e-4 + 2e-4 + 3e-4 + LINK_S),
        "compute_s": 1e-4, "actuate_s": 2e-4, "link_s": LINK_S, "sense_s": 3e-4, "skipped": 0,
        "retries": 0,
    }  # fmt: skip  # unchanged: no gateway fields
    assert gateway == {
        **plain, "retries": 1, "gateway_s": GATEWAY_S, "radio_s": RADIO_S,
        "gateway_bus_s": LINK_S - GATEWAY_S - RADIO_S,
    }  # fmt: skip
    assert no_signals == {**plain, "gateway_s": GATEWAY_S, "radio_s": 0.0,
                          "gateway_bus_s": LINK_S - GATEWAY_S}  # fmt: skip
    for entry in (gateway, no_signals):  # the stages sum to the link round trip
        total = entry["gateway_bus_s"] + entry["gateway_s"] + entry["radio_s"]
        assert total == pytest.approx(entry["link_s"])
    no_answer = ticks[3]["agents"]["f1"]
    assert no_answer["gateway_s"] is None and no_answer["radio_s"] is None
    assert no_answer["gateway_bus_s"] is None and no_answer["link_s"] == LINK_S


def test_plot_latency_splits_the_link_round_trip_when_recorded(ticks: list[dict]) -> None:
    parts = [key for key, _ in plotting.ledger_parts(ticks)]
    assert parts == ["compute_s", "actuate_s", "link_s", "gateway_bus_s", "gateway_s",
                     "radio_s", "sense_s", "bus_s"]  # fmt: skip
    ledger = plotting.tick_ledger(ticks)
    link, hops, gateway, radio = 2, 3, 4, 5
    _, f1 = ledger["f1"]
    assert f1[4, link] == pytest.approx(0.0, abs=1e-12)  # the stages explain all of it
    assert f1[4, [hops, gateway, radio]].tolist() == pytest.approx(
        [LINK_S - GATEWAY_S - RADIO_S, GATEWAY_S, RADIO_S]
    )
    assert f1[3, link] == LINK_S and f1[3, [hops, gateway, radio]].tolist() == [0.0] * 3
    _, leader = ledger["leader"]  # no gateway: its link stays the board link
    assert leader[4, link] == LINK_S and leader[4, [hops, gateway, radio]].tolist() == [0.0] * 3
    plain = [
        {"t": m["t"], "agents": {"leader": m["agents"]["leader"]}} for m in ticks
    ]  # a recording without the gateway: the ledger as before
    assert plotting.ledger_parts(plain) == plotting.LEDGER_PARTS
    assert plotting.tick_ledger(plain)["leader"][1].shape == (6, len(plotting.LEDGER_PARTS))


def test_stale_samples_are_a_note_never_a_degradation() -> None:
    def outcome(counters: dict) -> tuple[int, list[str], list[str]]:
        summary = RunSummary(experiment="bcast", mode="lockstep", ticks=100, planned_ticks=100,
                             stop_reason="completed", counters=counters)  # fmt: skip
        result = decide(summary)
        return result.code, result.degradations, result.notes

    code, degradations, notes = outcome({"f1": {"stale_samples": 80}})
    assert code == CLEAN and not degradations
    stale = "stale samples (the XBee gateway answered from the robot's last samples)"
    assert notes == [f"agent f1: 80 {stale}"]
    code, degradations, _ = outcome({"f1": {"stale_samples": 80, "link_faults": 1}})
    assert code == DEGRADED  # a real fault beside them still degrades
    assert degradations == [f"agent f1: 1 link faults, 80 {stale}"]
