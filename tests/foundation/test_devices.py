"""Devices: pin registration through the PinManager, pinout checks, device semantics."""

from __future__ import annotations

import pytest
from hilswarm.agents.devices import (
    Actuator,
    Battery,
    Device,
    HBridgeMotor,
    InOut,
    LowBatteryEvent,
    OutputPin,
    Sensor,
    Servo,
)
from hilswarm.agents.errors import DeviceError, PinError
from hilswarm.agents.link.board import PinMode
from hilswarm.agents.link.sim_board import SimBoard
from hilswarm.agents.pins import PinManager

MOTOR_PINS = {
    "left_fwd": 4,
    "left_back": 7,
    "left_pwm": 5,
    "right_fwd": 8,
    "right_back": 12,
    "right_pwm": 6,
}


def motor(pm: PinManager | None = None, **options: object) -> HBridgeMotor:
    return HBridgeMotor(
        pm or PinManager(), "drive", MOTOR_PINS, motors=("left", "right"), **options
    )  # type: ignore[arg-type]


# ---------------------------------------------------------------- base class behaviour
def test_devices_register_binders_named_device_dot_role() -> None:
    pm = PinManager()
    drive = motor(pm)
    assert pm.find_device("drive") == {f"drive.{role}": pin for role, pin in MOTOR_PINS.items()}
    assert pm.find_binder("drive.left_pwm").mode is PinMode.PWM
    assert pm.find_binder("drive.left_fwd").mode is PinMode.DIGITAL_OUT
    assert drive.pinout == MOTOR_PINS and drive.pin("right_pwm") == 6
    drive.release()
    assert pm.used_pins() == []
    drive.release()  # idempotent


def test_missing_role_names_device_and_role() -> None:
    pins = dict(MOTOR_PINS)
    del pins["right_back"]
    with pytest.raises(DeviceError) as info:
        HBridgeMotor(PinManager(), "drive", pins, motors=("left", "right"))
    assert "'drive'" in str(info.value) and "right_back" in str(info.value)


def test_unknown_role_names_device_and_role() -> None:
    with pytest.raises(DeviceError) as info:
        Battery(PinManager(), "batt", {"pin": "A0", "pni": "A1"})
    assert "'batt'" in str(info.value) and "pni" in str(info.value)


@pytest.mark.parametrize("spec", ["Z3", 3.0, None, "A9", 40, True])
def test_malformed_pin_spec_names_device_and_role(spec: object) -> None:
    with pytest.raises(DeviceError) as info:
        OutputPin(PinManager(), "led", {"pin": spec})  # type: ignore[dict-item]
    assert "'led'" in str(info.value) and "'pin'" in str(info.value)


def test_pinout_must_be_a_mapping() -> None:
    with pytest.raises(DeviceError, match=r"'led'.*pinout"):
        OutputPin(PinManager(), "led", [("pin", 3)])  # type: ignore[arg-type]


def test_unknown_option_is_named() -> None:
    with pytest.raises(DeviceError) as info:
        Battery(PinManager(), "batt", {"pin": "A0"}, multiplyer=3)
    assert "multiplyer" in str(info.value) and "'batt'" in str(info.value)


def test_bad_device_name_and_duplicate_names() -> None:
    pm = PinManager()
    with pytest.raises(DeviceError, match="device name"):
        OutputPin(pm, "a.b", {"pin": 3})
    OutputPin(pm, "led", {"pin": 3})
    with pytest.raises(DeviceError, match=r"'led'.*unique"):
        OutputPin(pm, "led", {"pin": 4})


def test_pin_conflict_between_devices_is_a_pin_error_and_rolls_back() -> None:
    pm = PinManager()
    Servo(pm, "rudder", {"pin": 9})
    pins = dict(MOTOR_PINS, right_pwm=10)  # Timer1 partner of the servo
    with pytest.raises(PinError) as info:
        HBridgeMotor(pm, "drive", pins, motors=("left", "right"))
    message = str(info.value)
    assert "drive.right_pwm" in message and "rudder.pin" in message
    assert pm.devices() == ["rudder"]  # the motor's already-bound pins were released
    motor(pm)  # and the same pins can now be used properly


def test_device_classes_are_abstract() -> None:
    assert issubclass(InOut, Actuator) and issubclass(InOut, Sensor)
    with pytest.raises(TypeError):
        Device(PinManager(), "x", {})  # type: ignore[abstract]


class Ranger(InOut):
    """An ultrasonic ranger: trigger out, echo in (a user-defined InOut)."""

    roles = ("trigger", "echo")

    def role_mode(self, role: str) -> PinMode:
        return PinMode.DIGITAL_OUT if role == "trigger" else PinMode.DIGITAL_IN

    def actuate(self, on: bool) -> None:
        self.write("trigger", int(on))

    def sense(self) -> int:
        return self.read("echo")


def test_user_defined_inout_device_on_a_board() -> None:
    pm = PinManager()
    ranger = Ranger(pm, "ranger", {"trigger": 2, "echo": "D3"})
    board = SimBoard(dt=0.01)
    pm.attach(board, watchdog_s=0)
    board.set_digital_input(3, 1)
    ranger.actuate(True)
    pm.exchange()
    assert board.outputs == {2: 1} and ranger.sense() == 1
    ranger.safe()
    assert pm.outputs == {2: 0}
    with pytest.raises(DeviceError, match=r"'ranger'.*'nope'"):
        ranger.write("nope", 1)


# ---------------------------------------------------------------- HBridgeMotor
@pytest.mark.parametrize(
    ("command", "fwd", "back", "pwm"),
    [(200, 1, 0, 200), (-120.4, 0, 1, 120), (0, 0, 0, 0), (999, 1, 0, 255), (-999, 0, 1, 255)],
)
def test_hbridge_signed_duty_sets_direction_and_pwm(
    command: float, fwd: int, back: int, pwm: int
) -> None:
    pm = PinManager()
    drive = motor(pm)
    applied = drive.actuate("left", command)
    assert pm.outputs[4] == fwd and pm.outputs[7] == back and pm.outputs[5] == pwm
    assert applied == (pwm if command >= 0 else -pwm)
    assert drive.duty("left") == applied


def test_hbridge_device_level_max_duty_clips() -> None:
    pm = PinManager()
    drive = motor(pm, max_duty={"left": 100})
    assert drive.actuate("left", 180) == 100 and pm.outputs[5] == 100
    assert drive.actuate("right", -300) == -255
    other = HBridgeMotor(PinManager(), "d", MOTOR_PINS, motors=("left", "right"), max_duty=80)
    assert other.actuate("right", -300) == -80


def test_hbridge_safe_state_is_both_directions_low_and_no_duty() -> None:
    pm = PinManager()
    drive = motor(pm)
    drive.actuate("left", 200)
    drive.actuate("right", -200)
    drive.safe()
    assert set(pm.outputs.values()) == {0}


@pytest.mark.parametrize(
    ("kwargs", "culprit"),
    [
        ({"motors": ()}, "motors"),
        ({"motors": "left"}, "motors"),
        ({"motors": ("left", "left")}, "repeat"),
        ({"motors": ("le ft",)}, "le ft"),
        ({"motors": ("left", "right"), "max_duty": 300}, "300"),
        ({"motors": ("left", "right"), "max_duty": {"center": 3}}, "center"),
    ],
)
def test_hbridge_bad_options_are_named(kwargs: dict, culprit: str) -> None:
    with pytest.raises(DeviceError, match=culprit):
        HBridgeMotor(PinManager(), "drive", MOTOR_PINS, **kwargs)


def test_hbridge_bad_commands_are_named() -> None:
    drive = motor()
    with pytest.raises(DeviceError, match="'center'"):
        drive.actuate("center", 10)
    with pytest.raises(DeviceError, match="nan"):
        drive.actuate("left", float("nan"))
    with pytest.raises(DeviceError, match="'fast'"):
        drive.actuate("left", "fast")


# ---------------------------------------------------------------- Servo
def test_servo_maps_angle_to_pulse_and_back() -> None:
    pm = PinManager()
    servo = Servo(pm, "rudder", {"pin": 9}, min_pulse_us=1000, max_pulse_us=2000)
    assert servo.angle_to_pulse(0) == 1000 and servo.angle_to_pulse(180) == 2000
    assert servo.angle_to_pulse(90) == 1500
    assert servo.pulse_to_angle(1250) == pytest.approx(45.0)
    assert pm.outputs == {9: 1500}  # safe value = neutral
    assert servo.actuate(45) == 45 and pm.outputs == {9: 1250}


def test_servo_default_mapping_is_the_arduino_library() -> None:
    servo = Servo(PinManager(), "s", {"pin": 10})
    assert servo.angle_to_pulse(0) == 544 and servo.angle_to_pulse(180) == 2400


def test_servo_angle_limits_clip_and_neutral_is_safe() -> None:
    pm = PinManager()
    servo = Servo(pm, "s", {"pin": 9}, angle_limits_deg=(30, 150), neutral_deg=60)
    assert servo.actuate(0) == 30 and servo.actuate(170) == 150
    servo.safe()
    assert servo.angle_deg == 60 and pm.outputs[9] == servo.angle_to_pulse(60)


@pytest.mark.parametrize(
    ("kwargs", "culprit"),
    [
        ({"min_pulse_us": 400}, "pulse"),
        ({"min_pulse_us": 2000, "max_pulse_us": 1000}, "pulse"),
        ({"min_angle_deg": 90, "max_angle_deg": 0}, "min_angle_deg"),
        ({"angle_limits_deg": (-10, 90)}, "angle_limits_deg"),
        ({"angle_limits_deg": 5}, "angle_limits_deg"),
        ({"neutral_deg": 200}, "neutral_deg"),
        ({"max_pulse_us": float("inf")}, "max_pulse_us"),
    ],
)
def test_servo_bad_options_are_named(kwargs: dict, culprit: str) -> None:
    with pytest.raises(DeviceError, match=culprit):
        Servo(PinManager(), "s", {"pin": 9}, **kwargs)


@pytest.mark.parametrize("pin", [3, 11, "A0"])
def test_servo_only_on_timer1_pins(pin: int | str) -> None:
    with pytest.raises(PinError, match=r"s\.pin"):
        Servo(PinManager(), "s", {"pin": pin})


def test_servo_bad_angle_is_named() -> None:
    with pytest.raises(DeviceError, match=r"'s'.*angle"):
        Servo(PinManager(), "s", {"pin": 9}).actuate(float("inf"))


# ---------------------------------------------------------------- OutputPin
def test_output_pin_digital_and_pwm() -> None:
    pm = PinManager()
    standby = OutputPin(pm, "standby", {"pin": 13})
    led = OutputPin(pm, "led", {"pin": 3}, mode="pwm", max_value=100, safe_value=5)
    assert pm.outputs == {3: 5, 13: 0}
    assert standby.actuate(True) == 1 and led.actuate(250) == 100
    assert pm.outputs == {3: 100, 13: 1}
    led.safe()
    standby.safe()
    assert pm.outputs == {3: 5, 13: 0}
    with pytest.raises(DeviceError, match=r"'standby'.*0/1"):
        standby.actuate(0.5)
    with pytest.raises(PinError, match=r"led2\.pin"):
        OutputPin(pm, "led2", {"pin": 4}, mode="pwm")


@pytest.mark.parametrize(
    ("kwargs", "culprit"),
    [
        ({"mode": "analog"}, "analog"),
        ({"mode": "pwm", "max_value": 256}, "256"),
        ({"max_value": 1}, "max_value"),
        ({"safe_value": 2}, "safe_value"),
    ],
)
def test_output_pin_bad_options(kwargs: dict, culprit: str) -> None:
    with pytest.raises(DeviceError, match=culprit):
        OutputPin(PinManager(), "led", {"pin": 3}, **kwargs)


# ---------------------------------------------------------------- Battery
def battery_on_board(**options: object) -> tuple[Battery, SimBoard, PinManager]:
    pm = PinManager(str(options.pop("profile", "uno")))
    battery = Battery(pm, "batt", {"pin": "A0"}, **options)  # type: ignore[arg-type]
    board = SimBoard(pm.profile, dt=0.01)
    pm.attach(board, watchdog_s=0)
    return battery, board, pm


def test_battery_converts_counts_with_vref_and_multiplier() -> None:
    battery, board, pm = battery_on_board(multiplier=3.0)
    board.set_analog_input(14, 2.5)
    pm.exchange()
    assert battery.sense() == pytest.approx(512 / 1023 * 5.0 * 3.0)
    assert battery.volts == pytest.approx(battery.sense())


def test_battery_vref_defaults_to_the_profile() -> None:
    battery, board, pm = battery_on_board(profile="fio")
    assert battery.vref_v == 3.3
    board.set_analog_input(14, 3.3)
    pm.exchange()
    assert battery.sense() == pytest.approx(3.3)


def test_low_battery_event_fires_once_per_crossing() -> None:
    battery, board, pm = battery_on_board(multiplier=2.0, low_v=6.0, hysteresis_v=0.5)
    events: list[LowBatteryEvent] = []
    battery.add_listener(events.append)
    volts_sequence = [8.0, 6.5, 5.9, 5.5, 6.2, 5.8, 6.6, 5.0, 4.0]
    for volts in volts_sequence:
        board.set_analog_input(14, volts / 2.0)
        pm.exchange()
        battery.sense()
    # crossings: 6.5 -> 5.9 fires; 6.2 is inside the hysteresis (no re-arm); 6.6 re-arms;
    # 5.0 fires again
    assert [round(e.volts, 1) for e in events] == [5.9, 5.0]
    assert all(e.device == "batt" and e.low_v == 6.0 for e in events)
    assert battery.is_low
    battery.remove_listener(events.append)


def test_battery_reads_before_an_exchange_are_clear_errors() -> None:
    battery = Battery(PinManager(), "batt", {"pin": "A0"})
    with pytest.raises(PinError, match=r"batt\.pin.*exchange"):
        battery.sense()


@pytest.mark.parametrize(
    ("kwargs", "culprit"),
    [
        ({"multiplier": 0}, "multiplier"),
        ({"vref_v": -5}, "vref_v"),
        ({"low_v": float("nan")}, "low_v"),
        ({"hysteresis_v": -1}, "hysteresis_v"),
    ],
)
def test_battery_bad_options_are_named(kwargs: dict, culprit: str) -> None:
    with pytest.raises(DeviceError, match=culprit):
        Battery(PinManager(), "batt", {"pin": "A0"}, **kwargs)


def test_battery_needs_an_analog_pin_and_callable_listeners() -> None:
    with pytest.raises(PinError, match=r"batt\.pin"):
        Battery(PinManager(), "batt", {"pin": 5})
    with pytest.raises(DeviceError, match="callable"):
        Battery(PinManager(), "batt", {"pin": "A1"}).add_listener(42)  # type: ignore[arg-type]


def test_remaining_device_errors_are_named() -> None:
    drive = motor()
    with pytest.raises(DeviceError, match="'center'"):
        drive.duty("center")
    led = OutputPin(PinManager(), "led", {"pin": 3}, mode="pwm")
    with pytest.raises(DeviceError, match=r"'led'.*not a number"):
        led.actuate("bright")  # type: ignore[arg-type]
    with pytest.raises(DeviceError, match=r"'led'.*not finite"):
        led.actuate(float("inf"))
    with pytest.raises(DeviceError, match="max_value"):
        OutputPin(PinManager(), "x", {"pin": 3}, max_value=1)
    with pytest.raises(DeviceError, match=r"'s'.*min_pulse_us"):
        Servo(PinManager(), "s", {"pin": 9}, min_pulse_us=True)  # type: ignore[arg-type]
    with pytest.raises(DeviceError, match="PinManager"):
        OutputPin({}, "x", {"pin": 3})  # type: ignore[arg-type]
    battery = Battery(PinManager(), "batt", {"pin": "A0"})
    battery.remove_listener(print)  # not registered: no error
    assert battery.volts is None and not battery.is_low
