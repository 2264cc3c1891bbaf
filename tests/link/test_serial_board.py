"""SerialBoard end to end: real bytes through a pty or a loopback socket to WireServer+SimBoard."""

from __future__ import annotations

import dataclasses
import threading
import time
from collections.abc import Iterator

import pytest
from hilswarm.agents.errors import (
    BoardConnectionError,
    BoardRequestError,
    BoardTimeoutError,
    ProtocolError,
)
from hilswarm.agents.link.board import (
    PROTOCOL_VERSION,
    BoardInfo,
    BoardStatus,
    ErrorCode,
    PinConfig,
    PinMode,
)
from hilswarm.agents.link.codec import SetIdReplyMsg
from hilswarm.agents.link.serial_board import (
    LinkEvent,
    SerialBoard,
    board_from_url,
    split_url_options,
)
from hilswarm.agents.link.sim_board import SimBoard
from hilswarm.agents.link.url import board_for_url
from hilswarm.agents.link.wire_server import PtyWireServer, SocketWireServer, WireServer

BLIMP = [
    *(PinConfig(p, PinMode.DIGITAL_OUT) for p in (2, 4, 7, 8, 12, 13)),
    PinConfig(5, PinMode.PWM),
    PinConfig(6, PinMode.PWM),
    PinConfig(9, PinMode.SERVO, 1500),
    PinConfig(14, PinMode.ANALOG_IN),
]
BLIMP_WRITES = {2: 1, 4: 0, 7: 1, 8: 0, 12: 1, 13: 0, 5: 200, 6: 17, 9: 1800}


def fast(url: str, **options: object) -> SerialBoard:
    """A board with short timeouts (loopback answers in well under a millisecond)."""
    defaults: dict[str, object] = {
        "timeout_s": 0.2,
        "retries": 2,
        "open_timeout_s": 1.0,
        "reconnect_timeout_s": 5.0,
    }
    return board_from_url(url, **(defaults | options))


@pytest.fixture
def sim() -> SimBoard:
    board = SimBoard("uno", dt=0.01, board_id=3)
    board.set_analog_input(14, 2.5)
    return board


@pytest.fixture
def pty_server(sim: SimBoard) -> Iterator[PtyWireServer]:
    with PtyWireServer(sim) as server:
        yield server
    assert server.failures == []


@pytest.fixture
def socket_server(sim: SimBoard) -> Iterator[SocketWireServer]:
    server = SocketWireServer(sim).start()
    yield server
    server.stop()
    assert server.failures == []


def test_handshake_configure_exchange_over_pty(pty_server: PtyWireServer, sim: SimBoard) -> None:
    events: list[LinkEvent] = []
    with fast(pty_server.url + "?board_id=3", on_event=events.append) as board:
        info = board.info
        assert info.protocol_version == PROTOCOL_VERSION == 2
        assert info.board_id == 3
        assert len(info.capabilities) == 20
        assert board.last_status & BoardStatus.RESET
        board.configure(BLIMP, watchdog_s=0.5)
        reply = board.exchange(BLIMP_WRITES, [14])
        assert reply.samples == {14: 512}  # 2.5 V of 5 V
        assert reply.status == BoardStatus.OK
        assert sim.outputs == BLIMP_WRITES
        # Digital outputs not written keep their last level (dout carries every one of them).
        board.exchange({5: 3}, [])
        assert sim.outputs[2] == 1 and sim.outputs[5] == 3
    assert [e.kind for e in events] == ["opened", "closed"]


def test_socket_url_through_board_for_url(socket_server: SocketWireServer) -> None:
    board = board_for_url(socket_server.url, timeout_s=0.2)
    assert isinstance(board, SerialBoard)
    with board:
        board.configure(BLIMP, watchdog_s=0)
        assert board.exchange(BLIMP_WRITES, [14]).samples == {14: 512}


def test_split_url_options() -> None:
    assert split_url_options("socket://127.0.0.1:5?board_id=3&logging=debug") == (
        "socket://127.0.0.1:5?logging=debug",
        {"board_id": 3},
    )
    assert split_url_options("/dev/ttyUSB0?baudrate=57600&timeout_s=0.5") == (
        "/dev/ttyUSB0",
        {"baudrate": 57600, "timeout_s": 0.5},
    )
    with pytest.raises(ValueError, match="board_id='x'"):
        split_url_options("/dev/ttyUSB0?board_id=x")
    with pytest.raises(ValueError, match="board_id"):
        board_from_url("/dev/ttyUSB0?board_id=3", board_id=3)
    with pytest.raises(ValueError, match="board_from_url"):
        SerialBoard("/dev/ttyUSB0?board_id=3")


class FutureBoard(SimBoard):
    """A board speaking a protocol version this host does not know."""

    def open(self) -> BoardInfo:
        return dataclasses.replace(super().open(), protocol_version=3)


class ProtocolOneBoard(SimBoard):
    """A board with protocol-1 firmware (no packed broadcast)."""

    def open(self) -> BoardInfo:
        return dataclasses.replace(super().open(), protocol_version=1)


def test_protocol_version_mismatch() -> None:
    with PtyWireServer(FutureBoard("uno", dt=0.01)) as server:
        board = fast(server.url)
        with pytest.raises(ProtocolError, match=r"protocol version 3.*versions \[1, 2\]"):
            board.open()
        assert not board.is_open


def test_a_protocol_1_board_still_works() -> None:
    with PtyWireServer(ProtocolOneBoard("uno", dt=0.01)) as server, fast(server.url) as board:
        assert board.info.protocol_version == 1
        board.configure(BLIMP, watchdog_s=0.5)  # a CONFIG without broadcast id: protocol 1
        assert board.exchange({5: 10}, [14]).samples.keys() == {14}


def test_board_id_mismatch(pty_server: PtyWireServer) -> None:
    with pytest.raises(ProtocolError, match="expected board id 4, the board reports id 3"):
        fast(pty_server.url + "?board_id=4").open()


def test_unopenable_port_names_the_url() -> None:
    with pytest.raises(BoardConnectionError, match="/dev/hilswarm-no-such-port"):
        fast("/dev/hilswarm-no-such-port").open()


def test_loop_url_hears_only_its_own_requests() -> None:
    # loop:// echoes: the host sees its own HELLO (a request type), discards it, times out.
    board = fast("loop://", timeout_s=0.05, retries=1, open_timeout_s=0.1)
    with pytest.raises(BoardTimeoutError, match="no reply"):
        board.open()
    assert board.stats.stale_replies >= 2


def test_retry_after_dropped_reply(pty_server: PtyWireServer, sim: SimBoard) -> None:
    with fast(pty_server.url) as board:
        board.configure(BLIMP, watchdog_s=0)
        pty_server.server.faults.drop_replies = 1
        reply = board.exchange(BLIMP_WRITES, [14])
        assert reply.samples == {14: 512}
        assert board.stats.retries == 1
        assert [e.kind for e in board.events].count("retry") == 1
        # The same seq was re-sent: the board applied the tick twice, idempotently.
        assert sim.exchange_count == 2


def test_retry_after_corrupted_reply_and_stale_duplicate(pty_server: PtyWireServer) -> None:
    with fast(pty_server.url) as board:
        board.configure(BLIMP, watchdog_s=0)
        pty_server.server.faults.corrupt_replies = 1
        first = board.exchange(BLIMP_WRITES, [14])
        assert board.stats.retries == 1
        pty_server.server.faults.duplicate_replies = 1
        second = board.exchange(BLIMP_WRITES, [14])
        third = board.exchange(BLIMP_WRITES, [14])  # must skip the stale copy of `second`
        assert [first.seq, second.seq, third.seq] == [
            first.seq,
            (first.seq + 1) % 256,
            (first.seq + 2) % 256,
        ]
        assert board.stats.stale_replies == 1
        assert "stale_reply" in [e.kind for e in board.events]


def test_timeout_after_all_retries_then_recovers(pty_server: PtyWireServer) -> None:
    with fast(pty_server.url, retries=2, timeout_s=0.05) as board:
        board.configure(BLIMP, watchdog_s=0)
        pty_server.server.faults.drop_replies = 3
        with pytest.raises(BoardTimeoutError, match="after 3 attempts"):
            board.exchange(BLIMP_WRITES, [14])
        assert board.exchange(BLIMP_WRITES, [14]).samples == {14: 512}


def test_reconnection_after_server_restart_reapplies_config(
    socket_server: SocketWireServer,
) -> None:
    events: list[LinkEvent] = []
    with fast(socket_server.url, on_event=events.append) as board:
        board.configure(BLIMP, watchdog_s=0.5)
        board.exchange(BLIMP_WRITES, [14])
        # The board goes away; a freshly booted one (no configuration) comes back.
        socket_server.stop()
        rebooted = SimBoard("uno", dt=0.01, board_id=3)
        rebooted.set_analog_input(14, 1.0)
        socket_server.server = WireServer(rebooted)
        restart = threading.Timer(0.3, socket_server.start)
        restart.start()
        try:
            reply = board.exchange(BLIMP_WRITES, [14])
        finally:
            restart.join(timeout=5)
        assert reply.samples == {14: round(1.0 / 5 * 1023)}
        assert rebooted.outputs == BLIMP_WRITES  # CONFIG was re-applied before the TICK
        assert rebooted.watchdog_s == 0.5
    kinds = [e.kind for e in events]
    assert kinds.index("disconnected") < kinds.index("reconnected")
    reconnected = next(e for e in events if e.kind == "reconnected")
    assert "re-applied" in reconnected.detail
    assert board.stats.reconnections == 1


def test_reconnection_gives_up_with_a_clear_error(socket_server: SocketWireServer) -> None:
    board = fast(socket_server.url, reconnect_timeout_s=0.3)
    board.open()
    board.configure(BLIMP, watchdog_s=0)
    socket_server.stop()
    with pytest.raises(BoardConnectionError, match=r"not re-established within 0\.3 s"):
        board.exchange(BLIMP_WRITES, [14])
    board.close()


def test_board_reboot_behind_open_port(pty_server: PtyWireServer, sim: SimBoard) -> None:
    with fast(pty_server.url) as board:
        board.configure(BLIMP, watchdog_s=0)
        board.exchange(BLIMP_WRITES, [14])
        pty_server.server.reboot()
        reply = board.exchange(BLIMP_WRITES, [14])
        assert reply.samples == {14: 512}
        assert sim.outputs == BLIMP_WRITES
        assert "board_reset" in [e.kind for e in board.events]


@pytest.mark.parametrize(
    ("pins", "code", "pin"),
    [
        ([PinConfig(4, PinMode.PWM)], ErrorCode.BAD_MODE, 4),
        ([PinConfig(0, PinMode.DIGITAL_OUT)], ErrorCode.BAD_PIN, 0),
        (
            [PinConfig(9, PinMode.SERVO, 1500), PinConfig(10, PinMode.PWM)],
            ErrorCode.PIN_CONFLICT,
            10,
        ),
        ([PinConfig(9, PinMode.SERVO, 100)], ErrorCode.BAD_VALUE, 9),
    ],
)
def test_config_error_frames(
    pty_server: PtyWireServer, pins: list[PinConfig], code: ErrorCode, pin: int
) -> None:
    with fast(pty_server.url) as board:
        with pytest.raises(BoardRequestError, match=code.name) as info:
            board.configure(pins, watchdog_s=0)
        assert (info.value.code, info.value.pin) == (code, pin)


def test_tick_and_raw_error_frames(pty_server: PtyWireServer) -> None:
    with fast(pty_server.url) as board:
        with pytest.raises(BoardRequestError, match="NOT_CONFIGURED") as info:
            board.exchange({}, [])
        assert info.value.code == ErrorCode.NOT_CONFIGURED
        board.configure(BLIMP, watchdog_s=0)
        with pytest.raises(BoardRequestError) as info:
            board.exchange({9: 3000}, [])
        assert (info.value.code, info.value.pin) == (ErrorCode.BAD_VALUE, 9)
        with pytest.raises(BoardRequestError) as info:
            board.exchange({}, [2])  # D2 is an output, not an input
        assert (info.value.code, info.value.pin) == (ErrorCode.BAD_PIN, 2)
        with pytest.raises(BoardRequestError) as info:
            board.exchange({3: 1}, [])  # not configured: refused before sending
        assert (info.value.code, info.value.pin) == (ErrorCode.BAD_PIN, 3)
        with pytest.raises(BoardRequestError, match="UNKNOWN_TYPE") as info:
            board.request(0x42)
        assert info.value.code == ErrorCode.UNKNOWN_TYPE
        with pytest.raises(BoardRequestError, match="BAD_LENGTH"):
            board.request(0x03, b"\x00\x00")
        with pytest.raises(BoardRequestError, match="BAD_LENGTH"):
            board.request(0x01, b"\x00")
        # After all those refusals the link works.
        assert board.exchange(BLIMP_WRITES, [14]).samples == {14: 512}


def test_garbage_on_the_line_is_reported_and_survived(pty_server: PtyWireServer) -> None:
    events: list[LinkEvent] = []
    with fast(pty_server.url, on_event=events.append) as board:
        board.configure(BLIMP, watchdog_s=0)
        board.write_raw(b"\x13\x37garbage\xff" + b"\x00")
        reply = board.exchange(BLIMP_WRITES, [14])
        assert reply.status & BoardStatus.RX_ERRORS
        assert "rx_errors" in [e.kind for e in events]
        assert not board.exchange(BLIMP_WRITES, [14]).status & BoardStatus.RX_ERRORS
        # A too-long frame is answered with ERROR FRAME_TOO_LONG (seq 0), which the host ignores.
        board.write_raw(b"\x07" * 150 + b"\x00")
        assert board.exchange(BLIMP_WRITES, [14]).samples == {14: 512}


def test_estop_and_set_id(pty_server: PtyWireServer, sim: SimBoard) -> None:
    safe = [*BLIMP[:-2], PinConfig(9, PinMode.SERVO, 1500), BLIMP[-1]]
    with fast(pty_server.url) as board:
        board.configure(safe, watchdog_s=0)
        board.exchange(BLIMP_WRITES, [14])
        reply = board.estop()
        assert reply.status & BoardStatus.ESTOPPED
        assert sim.outputs[9] == 1500 and sim.outputs[5] == 0
        held = board.exchange(BLIMP_WRITES, [14])
        assert held.status & BoardStatus.ESTOPPED
        assert sim.outputs[9] == 1500  # writes ignored while e-stopped
        board.configure(safe, watchdog_s=0)
        board.exchange(BLIMP_WRITES, [14])
        assert sim.outputs[9] == 1800
        assert board.set_board_id(77) == 77
        assert board.info.board_id == 77
        assert isinstance(board.request(0x05, (78).to_bytes(2, "little")), SetIdReplyMsg)
    with fast(pty_server.url + "?board_id=78") as again:
        assert again.info.board_id == 78


def test_request_estop_from_another_thread_while_an_exchange_waits(
    pty_server: PtyWireServer, sim: SimBoard
) -> None:
    """The e-stop's own path: written beside an exchange that waits for a lost reply; the
    board executes it at once; the exchange goes on waiting for its own reply."""
    with fast(pty_server.url, retries=3, timeout_s=0.2) as board:
        board.configure(BLIMP, watchdog_s=0)
        board.exchange(BLIMP_WRITES, [14])
        pty_server.server.faults.drop_replies = 1
        result: list[object] = []
        worker = threading.Thread(target=lambda: result.append(board.exchange(BLIMP_WRITES, [])))
        worker.start()
        deadline = time.monotonic() + 5
        while pty_server.server.faults.drop_replies and time.monotonic() < deadline:
            time.sleep(0.001)  # the exchange's first reply was dropped: it waits
        assert worker.is_alive()
        assert board.request_estop()
        deadline = time.monotonic() + 5
        while not sim.estopped and time.monotonic() < deadline:
            time.sleep(0.001)
        assert sim.estopped and sim.outputs[5] == 0  # safe while the exchange still waited
        worker.join(5)
        assert result and board.stats.stale_replies >= 1  # the ESTOP reply, discarded
        assert board.exchange(BLIMP_WRITES, []).status & BoardStatus.ESTOPPED


def test_an_estop_stays_latched_across_a_reconnection(
    socket_server: SocketWireServer, sim: SimBoard
) -> None:
    with fast(socket_server.url) as board:
        board.configure(BLIMP, watchdog_s=0)
        assert board.request_estop()
        socket_server.stop()
        socket_server.start()
        board.reconnect()  # re-applies the configuration (which clears an e-stop) ...
        assert sim.estopped  # ... and e-stops again
        board.configure(BLIMP, watchdog_s=0)  # an explicit configure clears it
        assert not sim.estopped


def test_abort_makes_a_waiting_request_give_up_at_once(pty_server: PtyWireServer) -> None:
    with fast(pty_server.url, retries=50, timeout_s=0.2) as board:
        board.configure(BLIMP, watchdog_s=0)
        pty_server.server.faults.drop_replies = 100
        errors: list[BaseException] = []

        def exchange() -> None:
            try:
                board.exchange(BLIMP_WRITES, [])
            except BoardConnectionError as exc:
                errors.append(exc)

        seen = pty_server.server.stats.requests
        worker = threading.Thread(target=exchange)
        worker.start()
        deadline = time.monotonic() + 5
        while pty_server.server.stats.requests == seen and time.monotonic() < deadline:
            time.sleep(0.001)  # until the board has the request: the exchange is waiting
        started = time.monotonic()
        board.abort()
        worker.join(5)
        assert time.monotonic() - started < 1.0 and errors  # not 51 x 0.2 s
        assert "aborted" in str(errors[0])
