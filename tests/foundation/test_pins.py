"""PinManager and board profiles: every rule of thesis §2.2.2, lookups, staging, board I/O."""

from __future__ import annotations

import pytest
from hilswarm.agents.errors import BoardConnectionError, HilswarmError, PinError
from hilswarm.agents.link.board import (
    PROTOCOL_VERSION,
    Board,
    BoardInfo,
    Capability,
    PinConfig,
    PinMode,
    TickReply,
)
from hilswarm.agents.link.sim_board import SimBoard
from hilswarm.agents.pins import PROFILES, PinAssignment, PinManager, parse_pin


def manager() -> PinManager:
    return PinManager("uno")


# ---------------------------------------------------------------- profiles and parse_pin
def test_profiles_match_the_atmega328_boards() -> None:
    for name in ("uno", "duemilanove", "fio"):
        profile = PROFILES[name]
        assert profile.pins == tuple(range(20))
        assert profile.pwm_pins == {3, 5, 6, 9, 10, 11}
        assert profile.servo_pins == {9, 10}
        assert profile.analog_pins == set(range(14, 20))
        assert profile.serial_pins == {0, 1}
    assert PROFILES["uno"].vref_v == 5.0
    assert PROFILES["duemilanove"].vref_v == 5.0
    assert PROFILES["fio"].vref_v == 3.3


def test_profile_capabilities_follow_the_protocol_table() -> None:
    caps = PROFILES["uno"].capabilities()
    assert caps[0] == caps[1] == Capability.RESERVED
    assert caps[2] == 0x03
    assert caps[3] == 0x07
    assert caps[9] == caps[10] == 0x0F
    assert all(caps[pin] == 0x13 for pin in range(14, 20))


@pytest.mark.parametrize(
    ("spec", "pin"), [(13, 13), ("D13", 13), ("d7", 7), ("A0", 14), ("a5", 19), ("12", 12)]
)
def test_parse_pin_accepts_numbers_and_names(spec: int | str, pin: int) -> None:
    assert parse_pin(spec, PROFILES["uno"]) == pin


@pytest.mark.parametrize(
    ("spec", "culprit"), [(25, "25"), ("A6", "A6"), ("X3", "X3"), (3.5, "3.5")]
)
def test_parse_pin_rejects_what_the_board_lacks(spec: object, culprit: str) -> None:
    with pytest.raises(PinError, match=culprit):
        parse_pin(spec, "uno")  # type: ignore[arg-type]


def test_unknown_profile_is_named() -> None:
    with pytest.raises(PinError, match="mega"):
        PinManager("mega")


def test_pin_error_is_a_value_error() -> None:
    assert issubclass(PinError, ValueError)
    assert issubclass(PinError, HilswarmError)


# ---------------------------------------------------------------- assignment rules
def test_assign_and_lookups() -> None:
    pm = manager()
    pm.assign(5, device="motor", binder="motor.left_pwm", mode=PinMode.PWM)
    pm.assign("D4", device="motor", binder="motor.left_fwd", mode=PinMode.DIGITAL_OUT)
    pm.assign("A0", device="battery", binder="battery.pin", mode=PinMode.ANALOG_IN)
    assert pm.is_assigned(5) and pm.is_assigned("A0") and not pm.is_assigned(6)
    assert pm.find_device("motor") == {"motor.left_pwm": 5, "motor.left_fwd": 4}
    assert pm.find_binder("battery.pin") == PinAssignment(
        14, "battery", "battery.pin", PinMode.ANALOG_IN, 0
    )
    assert pm.used_pins() == [4, 5, 14]
    assert pm.devices() == ["motor", "battery"]
    assert pm.pin_configs() == [
        PinConfig(4, PinMode.DIGITAL_OUT, 0),
        PinConfig(5, PinMode.PWM, 0),
        PinConfig(14, PinMode.ANALOG_IN, 0),
    ]


def test_pin_on_a_missing_pin_names_everything() -> None:
    with pytest.raises(PinError) as info:
        manager().assign(22, device="led", binder="led.pin", mode=PinMode.DIGITAL_OUT)
    assert "22" in str(info.value) and "led.pin" in str(info.value) and "'led'" in str(info.value)


@pytest.mark.parametrize("pin", [0, 1, "D0"])
def test_serial_pins_are_refused(pin: int | str) -> None:
    with pytest.raises(PinError) as info:
        manager().assign(pin, device="led", binder="led.pin", mode=PinMode.DIGITAL_OUT)
    message = str(info.value)
    assert "serial" in message and "led.pin" in message and "'led'" in message


def test_a_pin_is_bound_once_until_released() -> None:
    pm = manager()
    pm.assign(7, device="motor", binder="motor.fwd", mode=PinMode.DIGITAL_OUT)
    with pytest.raises(PinError) as info:
        pm.assign(7, device="sonar", binder="sonar.echo", mode=PinMode.DIGITAL_IN)
    message = str(info.value)
    for culprit in ("D7", "sonar.echo", "'sonar'", "motor.fwd", "'motor'", "already bound"):
        assert culprit in message
    pm.release(binder="motor.fwd")
    pm.assign(7, device="sonar", binder="sonar.echo", mode=PinMode.DIGITAL_IN)
    assert pm.find_binder("sonar.echo").pin == 7


def test_binder_names_are_unique() -> None:
    pm = manager()
    pm.assign(7, device="a", binder="shared", mode=PinMode.DIGITAL_OUT)
    with pytest.raises(PinError) as info:
        pm.assign(8, device="b", binder="shared", mode=PinMode.DIGITAL_OUT)
    message = str(info.value)
    assert "'shared'" in message and "D8" in message and "'b'" in message and "unique" in message


@pytest.mark.parametrize("pin", [2, 4, 7, 8, 12, 13, 14])
def test_pwm_only_on_pwm_pins(pin: int) -> None:
    with pytest.raises(PinError) as info:
        manager().assign(pin, device="m", binder="m.pwm", mode=PinMode.PWM)
    message = str(info.value)
    assert "no PWM" in message and "m.pwm" in message and "'m'" in message


@pytest.mark.parametrize("pin", [3, 5, 6, 11, 2])
def test_servo_only_on_servo_pins(pin: int) -> None:
    with pytest.raises(PinError) as info:
        manager().assign(pin, device="s", binder="s.pin", mode=PinMode.SERVO)
    message = str(info.value)
    assert "servo" in message and "s.pin" in message and "'s'" in message


def test_analog_input_only_on_analog_pins() -> None:
    with pytest.raises(PinError, match=r"D5.*no analog input|no analog input.*D5"):
        manager().assign(5, device="b", binder="b.pin", mode=PinMode.ANALOG_IN)


def test_analog_pins_work_as_digital_pins() -> None:
    pm = manager()
    pm.assign("A1", device="led", binder="led.pin", mode=PinMode.DIGITAL_OUT)
    pm.assign("A2", device="sw", binder="sw.pin", mode=PinMode.DIGITAL_IN_PULLUP)
    assert pm.used_pins() == [15, 16]


@pytest.mark.parametrize(("servo", "pwm"), [(9, 10), (10, 9)])
def test_servo_disables_pwm_on_its_timer1_partner_servo_first(servo: int, pwm: int) -> None:
    pm = manager()
    pm.assign(servo, device="servo", binder="servo.pin", mode=PinMode.SERVO, safe_value=1500)
    with pytest.raises(PinError) as info:
        pm.assign(pwm, device="motor", binder="motor.pwm", mode=PinMode.PWM)
    message = str(info.value)
    assert f"D{pwm}" in message and "servo.pin" in message and "motor.pwm" in message
    assert "Timer1" in message
    # digital use of the partner pin stays possible
    pm.assign(pwm, device="led", binder="led.pin", mode=PinMode.DIGITAL_OUT)


@pytest.mark.parametrize(("servo", "pwm"), [(9, 10), (10, 9)])
def test_servo_disables_pwm_on_its_timer1_partner_pwm_first(servo: int, pwm: int) -> None:
    pm = manager()
    pm.assign(pwm, device="motor", binder="motor.pwm", mode=PinMode.PWM)
    with pytest.raises(PinError) as info:
        pm.assign(servo, device="servo", binder="servo.pin", mode=PinMode.SERVO, safe_value=1500)
    message = str(info.value)
    assert f"D{servo}" in message and "servo.pin" in message and "motor.pwm" in message
    assert "Timer1" in message


def test_two_servos_share_timer1() -> None:
    pm = manager()
    pm.assign(9, device="a", binder="a.pin", mode=PinMode.SERVO, safe_value=1500)
    pm.assign(10, device="b", binder="b.pin", mode=PinMode.SERVO, safe_value=1500)
    assert pm.used_pins() == [9, 10]


@pytest.mark.parametrize(
    ("mode", "safe"),
    [(PinMode.DIGITAL_OUT, 2), (PinMode.PWM, 256), (PinMode.PWM, -1), (PinMode.SERVO, 400)],
)
def test_safe_values_are_range_checked(mode: PinMode, safe: int) -> None:
    with pytest.raises(PinError) as info:
        manager().assign(9, device="d", binder="d.pin", mode=mode, safe_value=safe)
    assert str(safe) in str(info.value) and "d.pin" in str(info.value)


def test_unused_mode_cannot_be_bound() -> None:
    with pytest.raises(PinError, match="UNUSED"):
        manager().assign(4, device="d", binder="d.pin", mode=PinMode.UNUSED)


def test_release_by_device_and_errors() -> None:
    pm = manager()
    pm.assign(4, device="m", binder="m.fwd", mode=PinMode.DIGITAL_OUT)
    pm.assign(5, device="m", binder="m.pwm", mode=PinMode.PWM)
    pm.release(device="m")
    assert pm.used_pins() == []
    with pytest.raises(PinError, match="'m'"):
        pm.release(device="m")
    with pytest.raises(PinError, match="'ghost'"):
        pm.release(binder="ghost")
    with pytest.raises(PinError, match="exactly one"):
        pm.release()
    with pytest.raises(PinError, match="exactly one"):
        pm.release(binder="a", device="b")


def test_unknown_lookups_name_the_culprit() -> None:
    pm = manager()
    with pytest.raises(PinError, match="'nobody'"):
        pm.find_device("nobody")
    with pytest.raises(PinError, match="'nothing'"):
        pm.find_binder("nothing")
    with pytest.raises(PinError, match="D6"):
        pm.assignment_of(6)


# ---------------------------------------------------------------- staging, reading
def test_write_stages_values_checked_per_mode() -> None:
    pm = manager()
    pm.assign(4, device="m", binder="m.fwd", mode=PinMode.DIGITAL_OUT)
    pm.assign(5, device="m", binder="m.pwm", mode=PinMode.PWM)
    pm.assign(9, device="s", binder="s.pin", mode=PinMode.SERVO, safe_value=1500)
    assert pm.outputs == {4: 0, 5: 0, 9: 1500}
    pm.write("m.fwd", True)
    pm.write("m.pwm", 200)
    pm.write("s.pin", 2000)
    assert pm.outputs == {4: 1, 5: 200, 9: 2000}
    assert pm.staged("m.pwm") == 200
    for binder, value in (("m.fwd", 2), ("m.pwm", 256), ("m.pwm", -3), ("s.pin", 499)):
        with pytest.raises(PinError) as info:
            pm.write(binder, value)
        assert binder in str(info.value) and str(value) in str(info.value)
    with pytest.raises(PinError, match="not an integer"):
        pm.write("m.pwm", 12.5)
    pm.drive_safe()
    assert pm.outputs == {4: 0, 5: 0, 9: 1500}


def test_no_writing_inputs_and_no_reading_outputs() -> None:
    pm = manager()
    pm.assign(4, device="m", binder="m.fwd", mode=PinMode.DIGITAL_OUT)
    pm.assign("A0", device="b", binder="b.pin", mode=PinMode.ANALOG_IN)
    with pytest.raises(PinError) as info:
        pm.write("b.pin", 1)
    assert "input" in str(info.value) and "b.pin" in str(info.value) and "A0" in str(info.value)
    with pytest.raises(PinError) as info:
        pm.read("m.fwd")
    assert "output" in str(info.value) and "m.fwd" in str(info.value) and "D4" in str(info.value)


def test_read_before_any_exchange_is_a_clear_error() -> None:
    pm = manager()
    pm.assign("A0", device="b", binder="b.pin", mode=PinMode.ANALOG_IN)
    with pytest.raises(PinError, match=r"no sample of pin A0.*b\.pin.*exchange"):
        pm.read("b.pin")


# ---------------------------------------------------------------- board
def test_attach_configures_and_exchange_batches_everything() -> None:
    pm = manager()
    pm.assign(4, device="m", binder="m.fwd", mode=PinMode.DIGITAL_OUT)
    pm.assign(5, device="m", binder="m.pwm", mode=PinMode.PWM)
    pm.assign("A0", device="b", binder="b.pin", mode=PinMode.ANALOG_IN)
    pm.assign(12, device="sw", binder="sw.pin", mode=PinMode.DIGITAL_IN_PULLUP)
    board = CountingSimBoard(dt=0.01)
    info = pm.attach(board, watchdog_s=0.2)
    assert info.protocol_version == PROTOCOL_VERSION  # the simulated board speaks the newest
    assert board.configuration == {c.pin: c for c in pm.pin_configs()}
    assert board.watchdog_s == pytest.approx(0.2)
    board.set_analog_input(14, 2.5)
    pm.write("m.fwd", 1)
    pm.write("m.pwm", 128)
    reply = pm.exchange()
    assert board.calls == [({4: 1, 5: 128}, [12, 14])]  # one exchange: all writes, all reads
    assert reply.samples == {12: 1, 14: round(2.5 / 5 * 1023)}
    assert pm.read("b.pin") == 512 and pm.read("sw.pin") == 1
    assert board.outputs == {4: 1, 5: 128}
    assert pm.last_reply == reply


def test_exchange_without_board_is_a_connection_error() -> None:
    with pytest.raises(BoardConnectionError, match="attach"):
        manager().exchange()


def test_changing_pins_after_attach_requires_attach_again() -> None:
    pm = manager()
    pm.assign(4, device="m", binder="m.fwd", mode=PinMode.DIGITAL_OUT)
    board = SimBoard(dt=0.01)
    pm.attach(board, watchdog_s=0)
    pm.assign(7, device="led", binder="led.pin", mode=PinMode.DIGITAL_OUT)
    with pytest.raises(PinError, match="attach"):
        pm.exchange()
    pm.attach(board, watchdog_s=0)
    pm.exchange()
    assert board.outputs == {4: 0, 7: 0}


class PoorBoard(SimBoard):
    """A board whose HELLO reports no PWM on pin 5 and no analog input at all."""

    def open(self) -> BoardInfo:
        info = super().open()
        caps = list(info.capabilities)
        caps[5] = Capability.DIGITAL_IN | Capability.DIGITAL_OUT
        caps[14] = Capability.DIGITAL_IN | Capability.DIGITAL_OUT
        return BoardInfo(info.protocol_version, info.firmware_version, info.board_id, tuple(caps))


def test_attach_checks_hello_capabilities_and_names_pin_and_capability() -> None:
    pm = manager()
    pm.assign(5, device="m", binder="m.pwm", mode=PinMode.PWM)
    with pytest.raises(PinError) as info:
        pm.attach(PoorBoard(dt=0.01, url="sim://poor"), watchdog_s=0)
    message = str(info.value)
    assert "D5" in message and "m.pwm" in message and "PWM" in message and "sim://poor" in message
    pm = manager()
    pm.assign("A0", device="b", binder="b.pin", mode=PinMode.ANALOG_IN)
    with pytest.raises(PinError, match=r"A0.*ANALOG_IN"):
        pm.attach(PoorBoard(dt=0.01), watchdog_s=0)


class CountingSimBoard(SimBoard):
    def __init__(self, **options: object) -> None:
        super().__init__(**options)  # type: ignore[arg-type]
        self.calls: list[tuple[dict[int, int], list[int]]] = []

    def exchange(self, writes, reads) -> TickReply:  # type: ignore[no-untyped-def]
        self.calls.append((dict(writes), list(reads)))
        return super().exchange(writes, reads)


def test_estop_through_the_manager() -> None:
    pm = manager()
    pm.assign(5, device="m", binder="m.pwm", mode=PinMode.PWM, safe_value=0)
    assert pm.estop() is None  # no board: only stages
    board = SimBoard(dt=0.01)
    pm.attach(board, watchdog_s=0)
    pm.write("m.pwm", 99)
    pm.exchange()
    assert board.outputs == {5: 99}
    reply = pm.estop()
    assert reply is not None and board.outputs == {5: 0} and board.estopped
    assert pm.outputs == {5: 0}


def test_board_is_an_abstract_interface() -> None:
    assert issubclass(SimBoard, Board)


# ---------------------------------------------------------------- remaining error paths
@pytest.mark.parametrize(
    ("kwargs", "culprit"),
    [
        ({"device": "", "binder": "x.pin", "mode": PinMode.DIGITAL_OUT}, "device name"),
        ({"device": "x", "binder": "", "mode": PinMode.DIGITAL_OUT}, "binder name"),
        ({"device": "x", "binder": "x.pin", "mode": 42}, "unknown pin mode 42"),
        ({"device": "x", "binder": "x.pin", "mode": PinMode.PWM, "safe_value": 1.5}, "1.5"),
        ({"device": "x", "binder": "x.pin", "mode": PinMode.DIGITAL_IN, "safe_value": 1}, "inputs"),
    ],
)
def test_assign_argument_errors_are_named(kwargs: dict, culprit: str) -> None:
    with pytest.raises(PinError) as info:
        manager().assign(3, **kwargs)
    assert culprit in str(info.value)


def test_staged_of_an_input_and_samples_before_exchange() -> None:
    pm = manager()
    pm.assign("A0", device="b", binder="b.pin", mode=PinMode.ANALOG_IN)
    with pytest.raises(PinError, match=r"b\.pin.*input"):
        pm.staged("b.pin")
    assert pm.samples() == {}


class ForgetfulBoard(SimBoard):
    """Answers without the samples it was asked for."""

    def exchange(self, writes, reads) -> TickReply:  # type: ignore[no-untyped-def]
        reply = super().exchange(writes, reads)
        return TickReply(reply.seq, reply.status, reply.board_time_s, {})


def test_reply_missing_samples_is_a_protocol_error() -> None:
    from hilswarm.agents.errors import ProtocolError

    pm = manager()
    pm.assign("A2", device="b", binder="b.pin", mode=PinMode.ANALOG_IN)
    pm.attach(ForgetfulBoard(dt=0.01, url="sim://forgetful"), watchdog_s=0)
    with pytest.raises(ProtocolError, match=r"sim://forgetful.*A2"):
        pm.exchange()


def test_detach_forgets_the_board() -> None:
    pm = manager()
    pm.attach(SimBoard(dt=0.01), watchdog_s=0)
    assert pm.board is not None
    pm.detach()
    with pytest.raises(BoardConnectionError):
        pm.exchange()
