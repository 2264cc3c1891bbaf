"""XBee gateway: how many robots one coordinator serves, against the computed bound.

Measured, each paired with its baseline (the load average is printed first; figures on a busy
machine are honest but low, ratios are what to compare):

1. **Hot-path codec**: encoding a TX Request and decoding an RX Packet, the small codec of
   ``agents/xbee/api_frames.py`` against Digi's ``digi-xbee`` packet classes [µs per frame].
2. **Bus hop**: the round trip an agent's frame makes to the gateway's process and back over
   the bus (``agent/<name>/link/tx`` -> a subscriber -> ``link/rx``) [ms], against a local
   call.
3. **Largest N with no late ticks** (unicast), at 20 and 50 Hz: N Frisbee-sized robots
   (``SimBoard`` behind ``WireServer``) on one simulated 115200-baud coordinator, the real
   gateway, N ``xbee://`` boards ticking together each period; a tick is late when not every
   reply is in within the period. Reported as a fraction of the computed bound (air and host
   UART, ``agents/xbee/budget.py``). Target: unicast >= 80 % of its bound.

    python benchmarks/xbee_gateway.py [--short] [--ticks K]
"""

from __future__ import annotations

import argparse
import os
import statistics
import threading
import time
from concurrent.futures import ThreadPoolExecutor

from digi.xbee.models.address import XBee64BitAddress
from digi.xbee.models.mode import OperatingMode
from digi.xbee.packets.factory import build_frame
from digi.xbee.packets.raw import TX64Packet
from hilswarm.agents import bus
from hilswarm.agents.errors import BoardError
from hilswarm.agents.link.board import PinConfig, PinMode
from hilswarm.agents.link.sim_board import SimBoard
from hilswarm.agents.xbee.air import AirParams, uart_s
from hilswarm.agents.xbee.api_frames import ApiFrameDecoder, Rx64Packet, Tx64Request, encode_frame
from hilswarm.agents.xbee.budget import RobotTraffic, gateway_budget, tick_frame_sizes
from hilswarm.agents.xbee.config import GatewayConfig
from hilswarm.agents.xbee.gateway import Gateway
from hilswarm.agents.xbee.sim_coordinator import SimCoordinator, SimRemote
from hilswarm.agents.xbee.sim_robot import WireServerUart
from hilswarm.agents.xbee.transport import board_from_url

FRISBEE = [
    PinConfig(7, PinMode.DIGITAL_OUT),
    PinConfig(8, PinMode.DIGITAL_OUT),
    PinConfig(4, PinMode.DIGITAL_OUT),
    PinConfig(12, PinMode.DIGITAL_OUT),
    PinConfig(5, PinMode.PWM),
    PinConfig(6, PinMode.PWM),
    PinConfig(14, PinMode.ANALOG_IN),
]
ADDRESS = 0x0013A20040000000
EXP = "xbee_bench"


def load() -> str:
    """The 1-minute load average and the core count."""
    return f"load {os.getloadavg()[0]:.2f} on {os.cpu_count()} cores"


def bench_codec(n: int) -> None:
    """Encode TX64 + decode RX64: our codec vs digi-xbee."""
    payload = bytes(range(16))
    rx_wire = encode_frame(Rx64Packet(ADDRESS + 1, -45, payload))
    decoder = ApiFrameDecoder()
    start = time.perf_counter()
    for i in range(n):
        encode_frame(Tx64Request(i % 255 + 1, ADDRESS + 1, payload))
        decoder.feed(rx_wire)
    ours = (time.perf_counter() - start) / n * 1e6

    dest = XBee64BitAddress.from_hex_string(f"{ADDRESS + 1:016X}")
    start = time.perf_counter()
    for i in range(n):
        TX64Packet(i % 255 + 1, dest, 0, rf_data=payload).output()
        build_frame(bytearray(rx_wire), OperatingMode.API_MODE)
    digi = (time.perf_counter() - start) / n * 1e6
    print(
        f"codec: ours {ours:.1f} us/frame pair, digi-xbee {digi:.1f} us/frame pair "
        f"(digi-xbee / ours = {digi / ours:.1f}x); {load()}"
    )


def bench_bus_hop(endpoint: str, n: int) -> None:
    """Round trip agent -> gateway-like subscriber -> agent over the bus."""
    keys = bus.BusKeys(EXP)
    far = bus.open_session(bus.client_config([endpoint]))
    near = bus.open_session(bus.client_config([endpoint]))
    back = far.declare_publisher(keys.link_rx("echo"), **bus.TICK_PATH_QOS)
    echo = far.declare_subscriber(keys.link_tx("echo"), lambda s: back.put(s.payload.to_bytes()))
    got = threading.Event()
    sub = near.declare_subscriber(keys.link_rx("echo"), lambda _s: got.set())
    pub = near.declare_publisher(keys.link_tx("echo"), **bus.TICK_PATH_QOS)
    time.sleep(0.3)  # benchmark only: let the declarations propagate
    times = []
    for _ in range(n):
        got.clear()
        t0 = time.perf_counter()
        pub.put(b"x" * 16)
        if got.wait(1.0):
            times.append(time.perf_counter() - t0)
    for entity in (sub, pub, echo, back):
        entity.undeclare()
    near.close()
    far.close()
    t0 = time.perf_counter()
    for _ in range(n):
        got.set()
    local = (time.perf_counter() - t0) / n
    print(
        f"bus hop (agent -> gateway -> agent): median {statistics.median(times) * 1e3:.2f} ms, "
        f"p95 {sorted(times)[int(0.95 * len(times))] * 1e3:.2f} ms over {len(times)} round "
        f"trips (a local call: {local * 1e6:.2f} us); {load()}"
    )


def bound(rate_hz: float) -> tuple[int, str]:
    """Largest N the budget allows at ``rate_hz`` and which resource binds."""
    request, reply = tick_frame_sizes(FRISBEE)
    n = 0
    binding = "air"
    while True:
        robots = [RobotTraffic(str(i), request, reply) for i in range(n + 1)]
        fractions = gateway_budget(robots, rate_hz=rate_hz).fractions()
        worst = max(fractions, key=lambda k: fractions[k])
        if fractions[worst] > 1.0:
            return n, binding
        n, binding = n + 1, worst


def ticks_on_time(
    endpoint: str, n: int, rate_hz: float, ticks: int
) -> tuple[int, int, list[float]]:
    """Run ``n`` robots at ``rate_hz`` for ``ticks``; return (late ticks, failed exchanges,
    tick durations [s])."""
    names = [f"r{i}" for i in range(n)]
    addresses = {name: ADDRESS + 1 + i for i, name in enumerate(names)}
    sims = [SimBoard(dt=1 / rate_hz) for _ in names]
    remotes = [SimRemote(addresses[nm], WireServerUart(sims[i])) for i, nm in enumerate(names)]
    session = bus.open_session(bus.client_config([endpoint]))
    boards = []
    late = failed = 0
    durations: list[float] = []
    dt = 1.0 / rate_hz
    with (
        SimCoordinator(remotes, seed=n) as coordinator,
        Gateway(GatewayConfig(), bus.BusKeys(EXP), addresses, session, port_url=coordinator.url),
        ThreadPoolExecutor(max_workers=n) as pool,
    ):
        try:
            for name in names:
                board = board_from_url(
                    f"xbee://{addresses[name]:016X}?timeout_s={dt}&retries=0",
                    endpoints=[endpoint],
                    experiment=EXP,
                    agent=name,
                )
                boards.append(board)
                board.open()
                board.configure(FRISBEE, watchdog_s=0)

            def one(board: object, k: int) -> bool:
                try:
                    board.exchange({5: k % 200, 6: 10, 7: k % 2}, [14])  # type: ignore[attr-defined]
                except BoardError:
                    return False
                return True

            next_t = time.monotonic()
            for k in range(ticks):
                futures = [pool.submit(one, b, k) for b in boards]
                ok = [f.result() for f in futures]
                failed += ok.count(False)
                done = time.monotonic()
                durations.append(done - next_t)
                if done - next_t > dt or not all(ok):
                    late += 1
                next_t += dt
                wait = next_t - time.monotonic()
                if wait > 0:
                    time.sleep(wait)  # the tick schedule (benchmark only)
                else:
                    next_t = time.monotonic()
        finally:
            for board in boards:
                board.close()
            session.close()
    return late, failed, durations


def latency_bound(rate_hz: float) -> tuple[int, float]:
    """Largest N whose tick also fits the fill and drain of one round trip: the first TX frame
    on the host UART, the robot's UART both ways, its packetization timeout, the last RX frame
    and its TX status (the air alone is the throughput bound of :func:`bound`). Returns
    (N, fixed latency [s])."""

    request, reply = tick_frame_sizes(FRISBEE)
    p = AirParams()
    fixed = (
        uart_s(15 + request, 115200)
        + uart_s(request, 115200)
        + uart_s(reply, 115200)
        + uart_s(p.packetization_chars, 115200)
        + uart_s(15 + reply + 7, 115200)
    )
    per_robot = p.mean_unicast_s(request) + p.mean_unicast_s(reply)
    return max(0, int((1.0 / rate_hz - fixed) // per_robot)), fixed


def bench_capacity(endpoint: str, rate_hz: float, ticks: int) -> None:
    """Largest N with no late ticks vs the computed bound."""
    n_bound, binding = bound(rate_hz)
    n_latency, fixed = latency_bound(rate_hz)
    best = best_1pc = 0
    for n in range(1, n_bound + 2):
        late, failed, durations = ticks_on_time(endpoint, n, rate_hz, ticks)
        durations.sort()
        print(
            f"  unicast {rate_hz:g} Hz, N={n}: {late}/{ticks} late ticks, {failed} failed; "
            f"tick p50 {durations[len(durations) // 2] * 1e3:.1f} ms, "
            f"max {durations[-1] * 1e3:.1f} ms"
        )
        if late == 0:
            best = n
        if late <= ticks // 100:
            best_1pc = n
        else:
            break
    print(f"  (largest N with at most 1 % late ticks: {best_1pc})")
    fraction = best / n_bound if n_bound else 0.0
    print(
        f"unicast at {rate_hz:g} Hz: largest N with no late tick {best}; computed bound "
        f"{n_bound} ({binding}): {fraction:.0%} of it (target >= 80 %); with one round trip's "
        f"fill and drain ({fixed * 1e3:.1f} ms) the bound is {n_latency}: "
        f"{best / n_latency if n_latency else 0:.0%} of it; {load()}"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--short", action="store_true", help="CI size (well under a minute)")
    parser.add_argument("--ticks", type=int, default=None, help="ticks per configuration")
    args = parser.parse_args()
    ticks = args.ticks or (20 if args.short else 200)
    print(load())
    bench_codec(2000 if args.short else 20000)
    router = bus.open_session(bus.listen_config([bus.loopback_endpoint(0)]))
    endpoint = bus.bound_endpoints(router)[0]  # the free port the router bound
    try:
        bench_bus_hop(endpoint, 100 if args.short else 1000)
        for rate in (20.0,) if args.short else (20.0, 50.0):
            bench_capacity(endpoint, rate, ticks)
    finally:
        router.close()


if __name__ == "__main__":
    main()
