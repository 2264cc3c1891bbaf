"""SimBoard: the firmware's checks and semantics (docs/protocol.md), stricter than hardware."""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np
import pytest
from hilswarm.agents.errors import (
    BoardConnectionError,
    BoardRequestError,
    LinkUrlError,
    PlantError,
)
from hilswarm.agents.link.board import (
    PROTOCOL_VERSION,
    BoardStatus,
    Capability,
    ErrorCode,
    PinConfig,
    PinMode,
)
from hilswarm.agents.link.sim_board import PinPlant, SimBoard, board_from_url
from hilswarm.agents.link.url import board_for_url

OUT = PinMode.DIGITAL_OUT


def opened(**options: object) -> SimBoard:
    board = SimBoard(**{"dt": 0.01, **options})  # type: ignore[arg-type]
    board.open()
    return board


def refused(code: ErrorCode, pin: int | None, call, *args, **kwargs) -> BoardRequestError:  # type: ignore[no-untyped-def]
    with pytest.raises(BoardRequestError) as info:
        call(*args, **kwargs)
    assert info.value.code == code, str(info.value)
    assert info.value.pin == pin
    assert code.name in str(info.value)
    return info.value


# ---------------------------------------------------------------- HELLO and URLs
def test_hello_reports_profile_capabilities_and_clears_reset() -> None:
    board = SimBoard("fio", dt=0.02, board_id=7)
    assert board.status & BoardStatus.RESET
    info = board.open()
    assert info.protocol_version == PROTOCOL_VERSION
    assert info.board_id == 7
    assert info.capabilities[0] == info.capabilities[1] == Capability.RESERVED
    assert info.capabilities[9] == 0x0F and info.capabilities[14] == 0x13
    assert not board.status & BoardStatus.RESET
    assert board.status & BoardStatus.NOT_CONFIGURED
    assert board.profile.vref_v == 3.3


def test_board_from_url_parses_profile_and_id() -> None:
    board = board_for_url("sim://fio?board_id=3", dt=0.05)
    assert isinstance(board, SimBoard)
    assert board.profile.name == "fio" and board.board_id == 3 and board.dt == 0.05
    assert board.url == "sim://fio?board_id=3"
    assert board_from_url("sim://", dt=0.1).profile.name == "uno"


@pytest.mark.parametrize(
    ("url", "culprit"),
    [
        ("sim://mega", "mega"),
        ("sim://uno?speed=3", "speed"),
        ("sim://uno?board_id=x", "board_id"),
        ("sim://uno?board_id=70000", "70000"),
        ("simavr://uno", "simavr"),
    ],
)
def test_bad_sim_urls_name_the_culprit(url: str, culprit: str) -> None:
    with pytest.raises(LinkUrlError, match=culprit):
        board_from_url(url, dt=0.01)


def test_bad_dt_and_plant_are_refused() -> None:
    with pytest.raises(LinkUrlError, match="dt"):
        SimBoard(dt=0.0)
    with pytest.raises(LinkUrlError, match="plant"):
        SimBoard(dt=0.01, plant=object())  # type: ignore[arg-type]


def test_requests_before_open_are_connection_errors() -> None:
    board = SimBoard(dt=0.01)
    with pytest.raises(BoardConnectionError):
        _ = board.info
    with pytest.raises(BoardConnectionError, match="open"):
        board.configure([], watchdog_s=0)
    with pytest.raises(BoardConnectionError, match="open"):
        board.exchange({}, [])
    board.open()
    board.close()
    board.close()  # idempotent
    with pytest.raises(BoardConnectionError):
        board.estop()


# ---------------------------------------------------------------- CONFIG checks
@pytest.mark.parametrize(
    ("pins", "code", "pin"),
    [
        ([PinConfig(20, OUT)], ErrorCode.BAD_PIN, 20),
        ([PinConfig(0, OUT)], ErrorCode.BAD_PIN, 0),
        ([PinConfig(1, PinMode.DIGITAL_IN)], ErrorCode.BAD_PIN, 1),
        ([PinConfig(4, OUT), PinConfig(4, PinMode.PWM)], ErrorCode.BAD_PIN, 4),
        ([PinConfig(4, PinMode.PWM)], ErrorCode.BAD_MODE, 4),
        ([PinConfig(5, PinMode.SERVO)], ErrorCode.BAD_MODE, 5),
        ([PinConfig(7, PinMode.ANALOG_IN)], ErrorCode.BAD_MODE, 7),
        ([PinConfig(7, 9)], ErrorCode.BAD_MODE, 7),  # type: ignore[arg-type]
        (
            [PinConfig(9, PinMode.SERVO, 1500), PinConfig(10, PinMode.PWM)],
            ErrorCode.PIN_CONFLICT,
            10,
        ),
        (
            [PinConfig(9, PinMode.PWM), PinConfig(10, PinMode.SERVO, 1500)],
            ErrorCode.PIN_CONFLICT,
            9,
        ),
        ([PinConfig(4, OUT, 2)], ErrorCode.BAD_VALUE, 4),
        ([PinConfig(5, PinMode.PWM, 256)], ErrorCode.BAD_VALUE, 5),
        ([PinConfig(9, PinMode.SERVO, 0)], ErrorCode.BAD_VALUE, 9),
        ([PinConfig(9, PinMode.SERVO, 2501)], ErrorCode.BAD_VALUE, 9),
    ],
)
def test_config_is_validated_like_the_firmware(
    pins: list[PinConfig], code: ErrorCode, pin: int
) -> None:
    board = opened()
    board.configure([PinConfig(13, OUT, 1)], watchdog_s=0)
    refused(code, pin, board.configure, pins, watchdog_s=0)
    # nothing changed
    assert board.configuration == {13: PinConfig(13, OUT, 1)}


def test_config_checks_run_in_the_firmware_order() -> None:
    board = opened()
    # a reserved pin (BAD_PIN) and a bad mode elsewhere: BAD_PIN first, as the firmware
    refused(
        ErrorCode.BAD_PIN,
        0,
        board.configure,
        [PinConfig(4, PinMode.PWM), PinConfig(0, OUT)],
        watchdog_s=0,
    )


def test_watchdog_must_fit_the_wire() -> None:
    board = opened()
    refused(ErrorCode.BAD_VALUE, None, board.configure, [], watchdog_s=70.0)
    refused(ErrorCode.BAD_VALUE, None, board.configure, [], watchdog_s=-1)
    board.configure([], watchdog_s=0.0123)
    assert board.watchdog_s == pytest.approx(0.012)  # 1 ms resolution


def test_config_drives_safe_values_and_clears_estop() -> None:
    board = opened()
    board.configure(
        [
            PinConfig(5, PinMode.PWM, 10),
            PinConfig(9, PinMode.SERVO, 1500),
            PinConfig(14, PinMode.ANALOG_IN),
        ],
        watchdog_s=0,
    )
    assert board.outputs == {5: 10, 9: 1500}
    assert not board.status & BoardStatus.NOT_CONFIGURED
    board.estop()
    assert board.estopped
    board.configure([PinConfig(5, PinMode.PWM, 0)], watchdog_s=0)
    assert not board.estopped and board.outputs == {5: 0}


# ---------------------------------------------------------------- TICK checks
def configured() -> SimBoard:
    board = opened()
    board.configure(
        [
            PinConfig(4, OUT),
            PinConfig(5, PinMode.PWM),
            PinConfig(9, PinMode.SERVO, 1500),
            PinConfig(12, PinMode.DIGITAL_IN),
            PinConfig(14, PinMode.ANALOG_IN),
        ],
        watchdog_s=0,
    )
    return board


def test_tick_before_config_is_not_configured() -> None:
    refused(ErrorCode.NOT_CONFIGURED, None, opened().exchange, {}, [])


@pytest.mark.parametrize(
    ("writes", "reads", "code", "pin"),
    [
        ({7: 1}, [], ErrorCode.BAD_PIN, 7),  # unconfigured
        ({12: 1}, [], ErrorCode.BAD_PIN, 12),  # an input
        ({14: 100}, [], ErrorCode.BAD_PIN, 14),
        ({}, [4], ErrorCode.BAD_PIN, 4),  # read of an output
        ({}, [6], ErrorCode.BAD_PIN, 6),  # read of an unconfigured pin
        ({}, [14, 14], ErrorCode.BAD_PIN, 14),  # read twice
        ({4: 2}, [], ErrorCode.BAD_VALUE, 4),
        ({5: 256}, [], ErrorCode.BAD_VALUE, 5),
        ({5: -1}, [], ErrorCode.BAD_VALUE, 5),
        ({5: 12.5}, [], ErrorCode.BAD_VALUE, 5),
        ({9: 499}, [], ErrorCode.BAD_VALUE, 9),
        ({9: 2501}, [], ErrorCode.BAD_VALUE, 9),
    ],
)
def test_tick_is_validated_whole(writes: dict, reads: list, code: ErrorCode, pin: int) -> None:
    board = configured()
    good = {4: 1, 5: 99}
    refused(code, pin, board.exchange, {**good, **writes}, reads)
    # validated whole: the good writes of the refused request were not applied, no time passed
    assert board.outputs == {4: 0, 5: 0, 9: 1500}
    assert board.exchange_count == 0 and board.time_s == 0.0


def test_tick_applies_writes_samples_and_advances_time() -> None:
    board = configured()
    board.set_analog_input(14, 1.0)
    board.set_digital_input(12, 1)
    reply = board.exchange({4: 1, 5: 200, 9: 2000}, [14, 12])
    assert board.outputs == {4: 1, 5: 200, 9: 2000}
    assert reply.samples == {12: 1, 14: round(1.0 / 5.0 * 1023)}
    assert list(reply.samples) == [12, 14]  # ascending pin order
    assert reply.status == BoardStatus.OK
    assert reply.board_time_s == pytest.approx(0.01)
    second = board.exchange({}, [])
    assert second.board_time_s == pytest.approx(0.02)
    assert second.seq == (reply.seq + 1) & 0xFF
    assert board.outputs == {4: 1, 5: 200, 9: 2000}  # unwritten outputs keep their value


@pytest.mark.parametrize(
    ("volts", "counts"), [(-1.0, 0), (0.0, 0), (2.5, 512), (5.0, 1023), (7.0, 1023)]
)
def test_analog_samples_are_rounded_and_clipped(volts: float, counts: int) -> None:
    board = configured()
    board.set_analog_input(14, volts)
    assert board.exchange({}, [14]).samples[14] == counts


def test_pullup_inputs_read_high_when_nothing_drives_them() -> None:
    board = opened()
    board.configure(
        [PinConfig(2, PinMode.DIGITAL_IN_PULLUP), PinConfig(3, PinMode.DIGITAL_IN)], watchdog_s=0
    )
    assert board.exchange({}, [2, 3]).samples == {2: 1, 3: 0}


# ---------------------------------------------------------------- plant
class RcPlant:
    """A motor draining a battery: voltage on A0 drops with the PWM duty on pin 5."""

    def __init__(self) -> None:
        self.battery_v = 4.0
        self.seen: list[tuple[dict[int, int], float]] = []

    def advance(self, outputs: Mapping[int, int], dt: float) -> Mapping[int, float]:
        self.seen.append((dict(outputs), dt))
        self.battery_v -= outputs.get(5, 0) / 255 * dt
        return {14: self.battery_v}

    def pose(self) -> np.ndarray:
        return np.zeros(6)


def test_plant_sees_outputs_and_closes_the_loop() -> None:
    plant = RcPlant()
    assert isinstance(plant, PinPlant)
    board = SimBoard(plant=plant, dt=0.5)
    board.open()
    board.configure([PinConfig(5, PinMode.PWM), PinConfig(14, PinMode.ANALOG_IN)], watchdog_s=0)
    samples = [board.exchange({5: 255}, [14]).samples[14] for _ in range(3)]
    assert plant.seen == [({5: 255}, 0.5)] * 3
    assert plant.battery_v == pytest.approx(2.5)
    assert samples == [round(v / 5 * 1023) for v in (3.5, 3.0, 2.5)]


class BadPlant(RcPlant):
    def advance(self, outputs: Mapping[int, int], dt: float) -> Mapping[int, float]:
        return {14: float("nan")}


def test_plant_returning_nonsense_is_named() -> None:
    board = SimBoard(plant=BadPlant(), dt=0.1)
    board.open()
    board.configure([PinConfig(14, PinMode.ANALOG_IN)], watchdog_s=0)
    with pytest.raises(PlantError, match="A0"):
        board.exchange({}, [14])


# ---------------------------------------------------------------- watchdog and e-stop
def test_watchdog_trips_on_link_silence_and_reports_once() -> None:
    plant = RcPlant()
    board = SimBoard(plant=plant, dt=0.02)
    board.open()
    board.configure([PinConfig(5, PinMode.PWM, 0), PinConfig(4, OUT, 1)], watchdog_s=0.1)
    board.exchange({5: 255, 4: 0}, [])
    board.advance_time(0.05)  # silence 0.07 s < 0.1 s
    assert board.outputs == {4: 0, 5: 255}
    board.advance_time(0.05)  # silence 0.12 s > 0.1 s: tripped at 0.1 s
    assert board.outputs == {4: 1, 5: 0}
    assert board.status & BoardStatus.WATCHDOG_TRIPPED
    # the plant saw PWM 255 exactly until the trip (t = 0.02 + 0.1), then safe values
    driven = sum(dt for outputs, dt in plant.seen if outputs[5] == 255)
    assert driven == pytest.approx(0.1)
    reply = board.exchange({5: 100, 4: 0}, [])
    assert reply.status & BoardStatus.WATCHDOG_TRIPPED  # reported once ...
    assert board.outputs == {4: 0, 5: 100}  # ... and the tick is applied normally
    assert not board.exchange({}, []).status & BoardStatus.WATCHDOG_TRIPPED


def test_watchdog_trips_every_tick_when_the_period_exceeds_it() -> None:
    board = SimBoard(dt=0.2)
    board.open()
    board.configure([PinConfig(5, PinMode.PWM)], watchdog_s=0.1)
    reply = board.exchange({5: 50}, [])
    assert reply.status & BoardStatus.WATCHDOG_TRIPPED and board.outputs == {5: 0}


def test_watchdog_zero_never_trips() -> None:
    board = configured()
    board.exchange({5: 50}, [])
    board.advance_time(100.0)
    assert board.outputs[5] == 50


def test_estop_latches_until_configure() -> None:
    board = configured()
    board.exchange({4: 1, 5: 99, 9: 2000}, [])
    reply = board.estop()
    assert reply.status & BoardStatus.ESTOPPED
    assert board.outputs == {4: 0, 5: 0, 9: 1500}
    board.set_analog_input(14, 5.0)
    tick = board.exchange({4: 1, 5: 99}, [14])  # writes ignored, samples still taken
    assert board.outputs == {4: 0, 5: 0, 9: 1500}
    assert tick.samples == {14: 1023} and tick.status & BoardStatus.ESTOPPED
    board.configure([PinConfig(5, PinMode.PWM)], watchdog_s=0)
    board.exchange({5: 99}, [])
    assert board.outputs == {5: 99} and not board.estopped


def test_power_cycle_loses_configuration_and_reports_reset() -> None:
    board = configured()
    board.exchange({}, [])
    board.power_cycle(hw_watchdog=True)
    assert board.status & BoardStatus.RESET and board.status & BoardStatus.HW_WATCHDOG_RESET
    assert board.status & BoardStatus.NOT_CONFIGURED and board.outputs == {}
    assert board.board_time_s == 0.0
    refused(ErrorCode.NOT_CONFIGURED, None, board.exchange, {}, [])
    board.open()
    assert not board.status & (BoardStatus.RESET | BoardStatus.HW_WATCHDOG_RESET)


def test_test_hooks_refuse_bad_input() -> None:
    board = configured()
    with pytest.raises(ValueError, match="25"):
        board.set_analog_input(25, 1.0)
    with pytest.raises(ValueError, match="level"):
        board.set_digital_input(12, 3)
    with pytest.raises(ValueError, match="seconds"):
        board.advance_time(-1)


def test_config_entries_must_be_pin_configs_and_at_most_twenty() -> None:
    board = opened()
    refused(ErrorCode.BAD_LENGTH, None, board.configure, [(4, 2, 0)], watchdog_s=0)
    refused(ErrorCode.BAD_LENGTH, None, board.configure, [PinConfig(4, OUT)] * 21, watchdog_s=0)


def test_tick_pins_that_are_not_numbers_are_bad_pins() -> None:
    board = configured()
    refused(ErrorCode.BAD_PIN, None, board.exchange, {"D4": 1}, [])
    refused(ErrorCode.BAD_PIN, None, board.exchange, {}, [None])


class StrayPlant(RcPlant):
    def advance(self, outputs: Mapping[int, int], dt: float) -> Mapping[int, float]:
        return {42: 1.0}


def test_plant_voltage_for_a_missing_pin_is_named() -> None:
    board = SimBoard(plant=StrayPlant(), dt=0.1)
    board.open()
    board.configure([], watchdog_s=0)
    with pytest.raises(PlantError, match="42"):
        board.exchange({}, [])
