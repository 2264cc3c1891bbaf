"""The 802.15.4 air model against the hand-computed figures (issue 12 / docs/xbee.md)."""

from __future__ import annotations

import statistics

import pytest
from hilswarm.agents.xbee.air import Air, AirModelError, AirParams, uart_s

A, B = 0x0013A20040000001, 0x0013A20040000002


def test_hand_computed_figures() -> None:
    p = AirParams()
    assert p.byte_s == pytest.approx(32e-6)
    assert p.frame_s(20) == pytest.approx((6 + 23 + 20) * 32e-6)  # 1.568 ms
    assert p.mean_backoff_s() == pytest.approx(1.12e-3)
    assert p.ack_s == pytest.approx(0.192e-3 + 11 * 32e-6)  # ~0.54 ms
    # an acknowledged unicast: 3.5-4 ms for ticks' payloads, so about 250/s at best
    assert p.mean_unicast_s(20) == pytest.approx(3.55e-3, abs=0.01e-3)
    assert 3.5e-3 <= p.mean_unicast_s(20) <= 4.0e-3
    assert 3.5e-3 <= p.mean_unicast_s(30) <= 4.0e-3
    assert 250 <= 1 / p.mean_unicast_s(30) <= 1 / p.mean_unicast_s(20) <= 290
    # host UART at 115200 8N1: 11.52 kB/s
    assert 1 / uart_s(1, 115200) == pytest.approx(11520)
    assert p.attempts == 4


def test_seeded_model_matches_the_mean_and_is_reproducible() -> None:
    def run(seed: int) -> list[float]:
        air = Air(seed=seed)
        now = 0.0
        times = []
        for _ in range(2000):
            tx = air.transmit(now, A, B, 20)
            times.append(tx.air_s)
            now = tx.end_s
        return times

    times = run(7)
    assert times == run(7)
    assert statistics.fmean(times) == pytest.approx(AirParams().mean_unicast_s(20), rel=0.05)


def test_shared_channel_serialises_packets() -> None:
    air = Air(seed=1)
    first = air.transmit(0.0, A, B, 20)
    second = air.transmit(0.0, B, A, 20)
    assert second.start_s == pytest.approx(first.end_s)


def test_out_of_range_spends_every_retry_and_fails() -> None:
    air = Air(seed=2)
    air.set_loss(A, B, 1.0)
    tx = air.transmit(0.0, A, B, 20)
    assert not tx.acked and tx.delivered_s is None and tx.attempts == 4
    assert air.stats.failures == 1
    air = Air(params=AirParams(xbee_retries=2), seed=2, default_loss=1.0)
    assert air.transmit(0.0, A, B, 10).attempts == 12


def test_lossy_link_retries() -> None:
    air = Air(seed=3, default_loss=0.3)
    results = [air.transmit(0.0, A, B, 20) for _ in range(1000)]
    retried = sum(r.retries > 0 for r in results)
    assert 300 < retried < 700  # 1 - 0.7 * 0.7 = 51 % need a retry
    assert all(r.delivered_s is not None for r in results if r.acked)


def test_broadcast_has_no_ack_and_no_retry() -> None:
    air = Air(seed=4, default_loss=1.0)
    tx = air.transmit(0.0, A, None, 90)
    assert tx.attempts == 1 and not tx.acked and tx.delivered_s is not None


def test_payload_limit() -> None:
    with pytest.raises(AirModelError, match=r"0\.\.100"):
        Air().transmit(0.0, A, B, 101)
