"""XBee gateway: how many robots one coordinator serves, against the computed bound.

Measured, each paired with its baseline (the load average is printed first; figures on a busy
machine are honest but low, ratios are what to compare):

1. **Hot-path codec**: encoding a TX Request and decoding an RX Packet, the small codec of
   ``agents/xbee/api_frames.py`` against Digi's ``digi-xbee`` packet classes [µs per frame].
2. **Bus hop**: the round trip an agent's frame makes to the gateway's process and back over
   the bus (``agent/<name>/link/tx`` -> a subscriber -> ``link/rx``) [ms], against a local
   call.
3. **Largest N with no late ticks**, unicast against the packed broadcast (``[gateway] mode =
   "broadcast"``, replies every ``--reply-every`` (5) ticks, round-robin), at 20 and 50 Hz: N
   Frisbee-sized robots (``SimBoard`` behind ``WireServer``) on one simulated 115200-baud
   coordinator, the real gateway, N ``xbee://`` boards ticking together each period (the
   simulated coordinator with its robots, and the gateway, each in a process of its own, as
   the radios and ``hilswarm run``'s gateway are; ``--one-process``: all in this one); a tick is
   late when not every reply is in within the period (a broadcast robot's reply on its reply
   ticks is its own fresh sample: the radio round trip); each mode also answering at once
   (``[gateway] answer = "at_once"``: every TICK answered from the robot's newest samples,
   marked stale), where a tick is late when not every robot drives its outputs within the
   period. Each N is reported as a fraction of
   two computed bounds: the throughput bound (air and host UART per tick,
   ``agents/xbee/budget.py``) and the latency bound (that, plus one tick's fill and drain: the
   frames through the host UART, the air, the robot's UART and back). Targets: unicast >= 80 %
   of its bound; broadcast >= 16 robots at 50 Hz.

    python benchmarks/xbee_gateway.py [--short] [--ticks K] [--reply-every M] [--one-process]
    python benchmarks/xbee_gateway.py --rates 50 --only broadcast --answers at_once
    python benchmarks/xbee_gateway.py --rates 20 --only unicast --answers at_once
"""

from __future__ import annotations

import argparse
import multiprocessing
import os
import statistics
import threading
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from concurrent.futures import ThreadPoolExecutor
from contextlib import ExitStack, contextmanager, suppress
from dataclasses import dataclass
from multiprocessing.connection import Connection

from digi.xbee.models.address import XBee64BitAddress
from digi.xbee.models.mode import OperatingMode
from digi.xbee.packets.factory import build_frame
from digi.xbee.packets.raw import TX64Packet
from hilswarm.agents import bus
from hilswarm.agents.errors import BoardError
from hilswarm.agents.link.board import BoardStatus, PinConfig, PinMode, TickReply
from hilswarm.agents.link.sim_board import SimBoard
from hilswarm.agents.xbee.api_frames import ApiFrameDecoder, Rx64Packet, Tx64Request, encode_frame
from hilswarm.agents.xbee.budget import (
    RobotTraffic,
    broadcast_budget,
    gateway_budget,
    section_size,
    tick_frame_sizes,
    tick_latency,
)
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


def _frisbees(n: int, reply_every: int = 1) -> list[RobotTraffic]:
    request, reply = tick_frame_sizes(FRISBEE)
    section = section_size(FRISBEE)
    return [RobotTraffic(str(i), request, reply, section, reply_every) for i in range(n)]


def bound(rate_hz: float) -> tuple[int, str]:
    """Largest N the budget allows at ``rate_hz`` and which resource binds."""
    n = 0
    binding = "air"
    while True:
        fractions = gateway_budget(_frisbees(n + 1), rate_hz=rate_hz).fractions()
        worst = max(fractions, key=lambda k: fractions[k])
        if fractions[worst] > 1.0:
            return n, binding
        n, binding = n + 1, worst


def bcast_bound(rate_hz: float, reply_every: int) -> tuple[int, str]:
    """Largest N the broadcast budget allows at ``rate_hz`` and which resource binds."""
    n = 0
    binding = "air"
    while n < 255:
        fractions = broadcast_budget(_frisbees(n + 1, reply_every), rate_hz=rate_hz).fractions()
        worst = max(fractions, key=lambda k: fractions[k])
        if fractions[worst] > 1.0:
            return n, binding
        n, binding = n + 1, worst
    return n, binding


def unicast_tick_s(n: int) -> float:
    """A unicast tick's fill and drain for ``n`` Frisbees [s] (the model of
    :func:`~hilswarm.agents.xbee.budget.tick_latency`, without the host's allowance)."""
    return tick_latency(gateway_budget(_frisbees(n), rate_hz=1.0)).radio_s


def bcast_tick_s(n: int, reply_every: int) -> float:
    """A broadcast tick's fill and drain [s] (model, :func:`tick_latency`): the BCAST frames
    through the host UART and the air, all of them through the robot's UART, the reply's UART
    and packetization, then the tick's replies one after the other on the air and the last
    one's RX frame on the host UART."""
    return tick_latency(broadcast_budget(_frisbees(n, reply_every), rate_hz=1.0)).radio_s


def bcast_delivery_s(n: int) -> float:
    """When the last robot has a tick's outputs (model, :func:`tick_latency`) [s]: the BCAST
    frames through the host UART and the air, and all of them through the robot's UART (what
    ``answer = "at_once"`` waits for: nothing else)."""
    budget = broadcast_budget(_frisbees(n), rate_hz=1.0)
    return tick_latency(budget, answer="at_once").radio_s


def largest_within(model: Callable[[int], float], period_s: float) -> int:
    """Largest N (at most 255) whose ``model(N)`` [s] fits ``period_s`` [s] (a latency bound:
    each model grows with N)."""
    n = 0
    while n < 255 and model(n + 1) <= period_s:
        n += 1
    return n


class TimedSimBoard(SimBoard):
    """A SimBoard that notes when each PWM-5 value reached it [s, monotonic]."""

    def __init__(self, **options: object) -> None:
        super().__init__(**options)  # type: ignore[arg-type]
        self.arrivals: list[tuple[float, int]] = []

    def exchange(self, writes: Mapping[int, int], reads: Sequence[int]) -> TickReply:
        """As SimBoard's; notes the arrival of ``writes[5]``."""
        if 5 in writes:
            self.arrivals.append((time.monotonic(), writes[5]))
        return super().exchange(writes, reads)


def delivery_s(arrivals: list[list[tuple[float, int]]], starts: list[float]) -> list[float]:
    """Per tick: when the last robot got the tick's outputs, after the tick started [s]
    (infinity: some robot never did); ``arrivals``: per robot, its ``TimedSimBoard``'s
    (times on CLOCK_MONOTONIC, one clock for every process here). Tick k writes PWM 5 =
    k % 250."""
    out = []
    for k, start in enumerate(starts):
        worst = 0.0
        for robot in arrivals:
            got = [t for t, v in robot if v == k % 250 and t >= start]
            worst = max(worst, (got[0] - start) if got else float("inf"))
        out.append(worst)
    return out


@dataclass
class TickRun:
    """What one configuration's run measured.

    Attributes:
        tick_s: per tick, the later of the slowest exchange and the delivery of the tick's
            outputs to the last robot, after the tick's start [s] (inf: never).
        failed_ticks: ticks with a failed exchange.
        failed: failed exchanges.
        stale: replies marked STALE.
        dt: the tick period [s].
    """

    tick_s: list[float]
    failed_ticks: list[bool]
    failed: int
    stale: int
    dt: float

    def late(self, periods: float = 1.0) -> int:
        """Ticks with a failure or not done within ``periods`` periods."""
        return sum(
            f or t > periods * self.dt for f, t in zip(self.failed_ticks, self.tick_s, strict=True)
        )


@dataclass(frozen=True)
class _GatewayRun:
    """How the gateway runs: ``[gateway] mode`` and ``answer``, every robot's ``reply_every``,
    the tick rate [Hz]."""

    mode: str
    answer: str
    reply_every: int
    rate_hz: float


@contextmanager
def _air(n: int, rate_hz: float) -> Iterator[tuple[str, list[TimedSimBoard]]]:
    """The simulated coordinator and ``n`` robots (``TimedSimBoard`` behind
    ``WireServerUart``, robot ``i`` at ``ADDRESS + 1 + i``): its pty's URL and the robots."""
    sims = [TimedSimBoard(dt=1 / rate_hz) for _ in range(n)]
    remotes = [SimRemote(ADDRESS + 1 + i, WireServerUart(sim)) for i, sim in enumerate(sims)]
    with SimCoordinator(remotes, seed=n) as coordinator:
        yield coordinator.url, sims


@contextmanager
def _gateway(
    endpoint: str, port_url: str, addresses: dict[str, int], run: _GatewayRun
) -> Iterator[None]:
    """The real gateway on ``port_url``, on the bus at ``endpoint``, with a session of its own."""
    session = bus.open_session(bus.client_config([endpoint]))
    try:
        with Gateway(
            GatewayConfig(mode=run.mode, answer=run.answer),
            bus.BusKeys(EXP),
            addresses,
            session,
            port_url=port_url,
            reply_every=dict.fromkeys(addresses, run.reply_every),
            rate_hz=run.rate_hz,
        ):
            yield
    finally:
        session.close()


def _serve_air(conn: Connection, n: int, rate_hz: float) -> None:
    """A process of its own: :func:`_air`; sends the pty's URL, waits for the word to stop,
    sends back each robot's ``arrivals``."""
    with _air(n, rate_hz) as (url, sims):
        conn.send(url)
        conn.recv()
    conn.send([sim.arrivals for sim in sims])


def _serve_gateway(
    conn: Connection, endpoint: str, port_url: str, addresses: dict[str, int], run: _GatewayRun
) -> None:
    """A process of its own: :func:`_gateway`; sends ``"ready"``, then runs until told to
    stop."""
    with _gateway(endpoint, port_url, addresses, run):
        conn.send("ready")
        conn.recv()


class _Helper:
    """A spawned process running ``target(conn, *args)`` (:func:`_in_process`)."""

    def __init__(self, target: object, args: tuple[object, ...], what: str) -> None:
        self.conn, theirs = multiprocessing.Pipe()
        self.what = what
        self.process = multiprocessing.get_context("spawn").Process(
            target=target, args=(theirs, *args), daemon=True
        )
        self.process.start()

    def first(self) -> object:
        """The first thing it sends (bounded wait)."""
        if not self.conn.poll(60.0):
            raise RuntimeError(f"the {self.what} process did not start within 60 s")
        try:
            return self.conn.recv()
        except EOFError:
            self.process.join(5.0)
            raise RuntimeError(
                f"the {self.what} process ended before it started (exit code "
                f"{self.process.exitcode}; its error is above)"
            ) from None

    def stop(self) -> object:
        """Tell it to stop; what it sends back then (``None``: nothing); wait for its end."""
        reply = None
        if self.process.is_alive():
            with suppress(BrokenPipeError, OSError):
                self.conn.send("stop")
            with suppress(EOFError, OSError):
                if self.conn.poll(30.0):
                    reply = self.conn.recv()
        self.process.join(10.0)
        if self.process.is_alive():
            self.process.kill()
            self.process.join(5.0)
        return reply


@contextmanager
def _in_process(target: object, args: tuple[object, ...], *, what: str) -> Iterator[_Helper]:
    """Start ``target(conn, *args)`` in a fresh (spawned) process; stopped at the end."""
    helper = _Helper(target, args, what)
    try:
        yield helper
    finally:
        helper.stop()


def ticks_on_time(
    endpoint: str,
    n: int,
    rate_hz: float,
    ticks: int,
    *,
    mode: str = "unicast",
    reply_every: int = 1,
    answer: str = "wait",
    processes: bool = True,
) -> TickRun:
    """Run ``n`` robots at ``rate_hz`` for ``ticks`` (at most 249) after one untimed tick.

    Tick k is done when every exchange returned and every robot drives tick k's outputs (with
    ``answer = "at_once"`` the answers do not wait for the air: the delivery is what says
    whether the radio keeps up). ``processes``: the simulated coordinator with its robots, and
    the gateway, each in a process of its own, as in a run (the radios are not on the host's
    CPU; the gateway is a process of ``hilswarm run``); else all in this one."""
    names = [f"r{i}" for i in range(n)]
    addresses = {name: ADDRESS + 1 + i for i, name in enumerate(names)}
    run = _GatewayRun(mode, answer, reply_every, rate_hz)
    sims: list[TimedSimBoard] = []
    boards = []
    failed = stale = 0
    exchange_s: list[float] = []
    failed_ticks: list[bool] = []
    starts: list[float] = []
    dt = 1.0 / rate_hz
    arrivals: list[list[tuple[float, int]]] = []
    with ExitStack() as stack:
        if processes:
            air = stack.enter_context(_in_process(_serve_air, (n, rate_hz), what="air"))
            port_url = air.first()
            gateway = stack.enter_context(
                _in_process(_serve_gateway, (endpoint, port_url, addresses, run), what="gateway")
            )
            gateway.first()
        else:
            port_url, sims = stack.enter_context(_air(n, rate_hz))
            stack.enter_context(_gateway(endpoint, port_url, addresses, run))
        pool = stack.enter_context(ThreadPoolExecutor(max_workers=n))
        try:
            for name in names:
                board = board_from_url(
                    f"xbee://{addresses[name]:016X}?timeout_s=0.5&retries=2",
                    endpoints=[endpoint],
                    experiment=EXP,
                    agent=name,
                )
                boards.append(board)
                board.open()
                board.configure(FRISBEE, watchdog_s=0)
                board.timeout_s, board.retries = dt, 0  # a tick's reply within its period

            def one(board: object, k: int) -> int:
                """1 fresh, 2 stale, 0 failed."""
                try:
                    reply = board.exchange({5: k % 250, 6: 10, 7: k % 2}, [14])  # type: ignore[attr-defined]
                except BoardError:
                    return 0
                return 2 if reply.status & BoardStatus.STALE else 1

            # one untimed tick first: in broadcast mode every robot answers the first one (the
            # gateway has no samples of it yet)
            for f in [pool.submit(one, b, 249) for b in boards]:
                f.result()
            time.sleep(dt)  # benchmark only: the warm-up tick's frames land
            next_t = time.monotonic()
            for k in range(ticks):
                starts.append(next_t)
                futures = [pool.submit(one, b, k) for b in boards]
                ok = [f.result() for f in futures]
                failed += ok.count(0)
                stale += ok.count(2)
                failed_ticks.append(not all(ok))
                exchange_s.append(time.monotonic() - next_t)
                next_t += dt
                wait = next_t - time.monotonic()
                if wait > 0:
                    time.sleep(wait)  # the tick schedule (benchmark only)
                else:
                    next_t = time.monotonic()
            time.sleep(0.3)  # benchmark only: the last ticks' frames land
        finally:
            for board in boards:
                board.close()
        if processes:
            gateway.stop()  # before its port goes
            arrivals = air.stop()  # type: ignore[assignment]
            if arrivals is None:
                raise RuntimeError("the air process did not send its robots' arrivals")
        else:
            arrivals = [sim.arrivals for sim in sims]
    delivered = delivery_s(arrivals, starts)
    tick_s = [max(a, b) for a, b in zip(exchange_s, delivered, strict=True)]
    return TickRun(tick_s, failed_ticks, failed, stale, dt)


def latency_bound(rate_hz: float) -> tuple[int, float]:
    """Largest N whose tick also fits the fill and drain of one round trip: the first TX frame
    on the host UART, the robot's UART both ways, its packetization timeout, the last RX frame
    and its TX status (the air alone is the throughput bound of :func:`bound`). Returns
    (N, fixed latency [s])."""
    return largest_within(unicast_tick_s, 1.0 / rate_hz), 2 * unicast_tick_s(1) - unicast_tick_s(2)


def unicast_delivery_s(n: int) -> float:
    """When the last of ``n`` Frisbees has a unicast tick's outputs, answering at once [s]
    (model, :func:`tick_latency`): the first TICK through the host UART, every robot's TICK
    and every other robot's reply on the air (the worst order), the last TICK through its
    robot's UART."""
    return tick_latency(gateway_budget(_frisbees(n), rate_hz=1.0), answer="at_once").radio_s


def bench_capacity(
    endpoint: str, rate_hz: float, ticks: int, *, answer: str = "wait", processes: bool = True
) -> None:
    """Largest N with no late ticks by unicast vs the computed bound; ``answer``: the
    gateway's ``answer`` (``"at_once"``: a tick is done when every robot drives its
    outputs)."""
    n_bound, binding = bound(rate_hz)
    n_latency, fixed = latency_bound(rate_hz)
    if answer == "at_once":  # the outputs' delivery is the latency that must fit
        n_latency = largest_within(unicast_delivery_s, 1.0 / rate_hz)
    best = best_1pc = 0
    for n in range(1, n_bound + 2):
        run = ticks_on_time(endpoint, n, rate_hz, ticks, answer=answer, processes=processes)
        late, failed, durations = run.late(), run.failed, sorted(run.tick_s)
        print(
            f"  unicast ({answer}) {rate_hz:g} Hz, N={n}: {late}/{ticks} late ticks, {failed} "
            f"failed, {run.stale}/{n * ticks} replies stale; "
            f"tick p50 {durations[len(durations) // 2] * 1e3:.1f} ms, "
            f"max {durations[-1] * 1e3:.1f} ms; {load()}"
        )
        if late == 0:
            best = n
        if late <= ticks // 100:
            best_1pc = n
        else:
            break
    print(f"  (largest N with at most 1 % late ticks: {best_1pc})")
    fraction = best / n_bound if n_bound else 0.0
    latency = (
        "answering at once, the bound on delivering every robot's outputs within the period"
        if answer == "at_once"
        else f"with one round trip's fill and drain ({fixed * 1e3:.1f} ms) the bound"
    )
    print(
        f"unicast ({answer}) at {rate_hz:g} Hz: largest N with no late tick {best}; computed "
        f"bound {n_bound} ({binding}): {fraction:.0%} of it (target >= 80 %); {latency} is "
        f"{n_latency}: {best / n_latency if n_latency else 0:.0%} of it; {load()}"
    )


def bench_broadcast(
    endpoint: str,
    rate_hz: float,
    ticks: int,
    reply_every: int,
    *,
    step: int,
    answer: str = "wait",
    max_n: int = 255,
    processes: bool = True,
) -> None:
    """Largest N (at most ``max_n``) with no late ticks by packed broadcast vs its bounds."""
    n_bound, binding = bcast_bound(rate_hz, reply_every)

    def model(n: int) -> float:
        """The latency that must fit the period: answering at once, the outputs' delivery."""
        return bcast_tick_s(n, reply_every) if answer == "wait" else bcast_delivery_s(n)

    n_latency = largest_within(model, 1.0 / rate_hz)

    best = best_1pc = best_2 = 0
    n = 1
    while n <= min(n_bound + 1, max_n):
        run = ticks_on_time(
            endpoint,
            n,
            rate_hz,
            ticks,
            mode="broadcast",
            reply_every=reply_every,
            answer=answer,
            processes=processes,
        )
        late, failed, stale, durations = run.late(), run.failed, run.stale, sorted(run.tick_s)
        print(
            f"  broadcast ({answer}) {rate_hz:g} Hz, reply_every {reply_every}, N={n}: "
            f"{late}/{ticks} late "
            f"ticks ({run.late(2.0)} not done within 2 periods), {failed} failed, "
            f"{stale}/{n * ticks} replies stale; tick p50 "
            f"{durations[len(durations) // 2] * 1e3:.1f} ms, max {durations[-1] * 1e3:.1f} ms "
            f"(model {model(n) * 1e3:.1f} ms); {load()}"
        )
        if late == 0:
            best = n
        if late <= ticks // 100:
            best_1pc = n
        if run.late(2.0) == 0:
            best_2 = n
        # at_once: go on while the radio keeps up (every tick's outputs within two periods)
        if (run.late(2.0) if answer == "at_once" else late) > ticks // 100:
            break
        n = n + step if n > 1 else step
    print(
        f"  (largest N with at most 1 % late ticks: {best_1pc}; with every tick's outputs "
        f"delivered within two periods: {best_2})"
    )
    print(
        f"broadcast ({answer}) at {rate_hz:g} Hz, reply_every {reply_every}: largest N with no "
        "late tick "
        f"{best} (step {step}); throughput bound {n_bound} ({binding}): "
        f"{best / n_bound if n_bound else 0:.0%} of it; latency bound (fill and drain) "
        f"{n_latency}: {best / n_latency if n_latency else 0:.0%} of it (target >= 16 at 50 Hz); "
        f"{load()}"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--short", action="store_true", help="CI size (well under a minute)")
    parser.add_argument("--ticks", type=int, default=None, help="ticks per configuration")
    parser.add_argument("--reply-every", type=int, default=5, help="broadcast: reply every M")
    parser.add_argument("--rates", type=float, nargs="+", default=None, help="tick rates [Hz]")
    parser.add_argument(
        "--only", choices=("unicast", "broadcast"), default=None, help="one mode's capacity"
    )
    parser.add_argument(
        "--one-process",
        action="store_true",
        help="the simulated air and the gateway in this process (the layout before: their "
        "threads share one interpreter with the boards'); default: each in a process of its own",
    )
    parser.add_argument(
        "--answers",
        choices=("wait", "at_once"),
        nargs="+",
        default=None,
        help="the gateway's answer modes to measure (default: both; --short: both by unicast, "
        "wait by broadcast)",
    )
    args = parser.parse_args()
    processes = not args.one_process
    ticks = min(args.ticks or (20 if args.short else 200), 249)
    print(f"{load()}; air and gateway: {'processes of their own' if processes else 'this process'}")
    bench_codec(2000 if args.short else 20000)
    router = bus.open_session(bus.listen_config([bus.loopback_endpoint(0)]))
    endpoint = bus.bound_endpoints(router)[0]  # the free port the router bound
    try:
        bench_bus_hop(endpoint, 100 if args.short else 1000)
        for rate in args.rates or ((20.0,) if args.short else (20.0, 50.0)):
            if args.only != "broadcast":
                for answer in args.answers or ("wait", "at_once"):
                    bench_capacity(endpoint, rate, ticks, answer=answer, processes=processes)
            if args.only != "unicast":
                step = 8 if args.short else (4 if rate < 30 else 2)
                answers = args.answers or (("wait",) if args.short else ("wait", "at_once"))
                for answer in answers:
                    bench_broadcast(
                        endpoint,
                        rate,
                        ticks,
                        args.reply_every,
                        step=step,
                        answer=answer,
                        max_n=16 if args.short else 255,
                        processes=processes,
                    )
    finally:
        router.close()


if __name__ == "__main__":
    main()
