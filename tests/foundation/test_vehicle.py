"""Vehicle: definition checks, pinout overrides, limits, calibration, the tick, safe mode."""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any, ClassVar

import numpy as np
import pytest
from hilswarm.agents.calibration import Calibration
from hilswarm.agents.devices import Battery, HBridgeMotor, OutputPin, Servo
from hilswarm.agents.errors import (
    CalibrationError,
    PinError,
    VehicleDefinitionError,
    VehicleError,
)
from hilswarm.agents.link.board import BoardStatus
from hilswarm.agents.link.sim_board import SimBoard
from hilswarm.agents.vehicle import BATTERY_CHANNEL, Vehicle

DRIVE_PINS = {
    "left_fwd": 4,
    "left_back": 7,
    "left_pwm": 5,
    "right_fwd": 8,
    "right_back": 12,
    "right_pwm": 6,
}


class Rover(Vehicle):
    """Two H-bridge motors and a battery; u = signed duty per motor, y = battery volts."""

    n_inputs = 2
    n_outputs = 1
    input_names = ("left", "right")
    output_names = ("battery_v",)
    default_pinout: ClassVar = {"drive": DRIVE_PINS, "battery": {"pin": "A0"}}
    default_params: ClassVar[dict[str, Any]] = {"low_v": 6.5, "max_duty": 255}

    def setup_devices(self) -> None:
        self.drive = self.add_device(
            HBridgeMotor, "drive", motors=("left", "right"), max_duty=self.params["max_duty"]
        )
        self.battery = self.add_device(
            Battery, "battery", multiplier=3.0, low_v=self.params["low_v"]
        )

    def setup_telemetry(self) -> None:
        self.telemetry.add_channel("duty", ("left", "right"))

    def read_outputs(self) -> list[float]:
        return [self.battery.sense()]

    def actuate(self, u: np.ndarray) -> np.ndarray:
        return np.array([self.drive.actuate("left", u[0]), self.drive.actuate("right", u[1])])

    def record_telemetry(self, k: int, t: float, y: np.ndarray) -> None:
        self.telemetry["duty"].append(k, t, [self.drive.duty("left"), self.drive.duty("right")])


class DrainingBattery:
    """PinPlant: an 8 V pack through a 1:3 divider on A0, drained by the two motors' duty."""

    def __init__(self, volts: float = 8.0, drain_v_per_s: float = 1.0) -> None:
        self.volts = volts
        self.drain = drain_v_per_s
        self.outputs_seen: list[dict[int, int]] = []

    def advance(self, outputs: Mapping[int, int], dt: float) -> Mapping[int, float]:
        self.outputs_seen.append(dict(outputs))
        load = (outputs.get(5, 0) + outputs.get(6, 0)) / (2 * 255)
        self.volts -= self.drain * load * dt
        return {14: self.volts / 3.0}

    def pose(self) -> np.ndarray:
        return np.zeros(6)


# ---------------------------------------------------------------- the integration test
def test_low_battery_puts_the_rover_in_safe_mode_with_safe_outputs_on_the_board() -> None:
    plant = DrainingBattery(volts=7.0, drain_v_per_s=2.0)
    board = SimBoard("uno", plant=plant, dt=0.05)
    rover = Rover(name="rover-1")
    reasons: list[str] = []
    rover.add_safe_mode_listener(reasons.append)
    rover.connect(board, watchdog_s=0.5)
    tick_of_safe_mode = None
    for k in range(40):
        y = rover.sense(k, k * 0.05)
        if rover.safe_mode and tick_of_safe_mode is None:
            tick_of_safe_mode = k
        rover.apply([255, -200])
        rover.exchange()
        if tick_of_safe_mode is None:
            assert board.outputs == {4: 1, 5: 255, 6: 200, 7: 0, 8: 0, 12: 1}
    assert tick_of_safe_mode is not None and 1 < tick_of_safe_mode < 40
    assert y[0] < 6.5
    # safe mode: every output at its safe value on the board, the board e-stopped, latched
    assert board.outputs == dict.fromkeys((4, 5, 6, 7, 8, 12), 0)
    assert board.estopped and board.status & BoardStatus.ESTOPPED
    assert rover.safe_mode and reasons == [rover.safe_mode_reason]
    assert "low battery" in reasons[0] and "battery" in reasons[0]
    assert rover.ignored_applies == 40 - tick_of_safe_mode
    assert rover.u.tolist() == [0.0, 0.0]
    # the plant saw the motors stop
    assert plant.outputs_seen[-1][5] == 0 and plant.outputs_seen[-1][6] == 0
    # telemetry: battery every tick, duty (the vehicle's own channel) every tick
    k, _, volts = rover.telemetry[BATTERY_CHANNEL].arrays()
    assert k.tolist() == list(range(40)) and volts[0, 0] == pytest.approx(7.0, abs=0.1)
    assert np.all(np.diff(volts[: tick_of_safe_mode + 1, 0]) < 0)
    assert rover.telemetry["duty"].arrays().values[0].tolist() == [0, 0]
    assert rover.telemetry["duty"].arrays().values[1].tolist() == [255, -200]


def test_watchdog_on_link_silence_makes_board_outputs_safe() -> None:
    board = SimBoard(plant=DrainingBattery(), dt=0.02)
    rover = Rover()
    rover.connect(board, watchdog_s=0.1)
    rover.sense(0, 0.0)
    rover.apply([100, 100])
    rover.exchange()
    assert board.outputs[5] == 100
    board.advance_time(0.5)  # the host went silent
    assert board.outputs[5] == 0 and board.outputs[4] == 0
    assert rover.exchange().status & BoardStatus.WATCHDOG_TRIPPED  # type: ignore[union-attr]


# ---------------------------------------------------------------- construction
def test_construction_needs_no_board_and_builds_devices() -> None:
    rover = Rover(name="r")
    assert rover.pins.used_pins() == [4, 5, 6, 7, 8, 12, 14]
    assert set(rover.devices) == {"drive", "battery"}
    assert rover.batteries == [rover.battery] and rover.actuators == [rover.drive]
    assert rover.pose_source is None
    assert rover.simulated_hardware(initial_state=None, dt=0.1) is None
    assert np.isnan(rover.y).all() and rover.u.tolist() == [0.0, 0.0]
    assert rover.telemetry.names == (BATTERY_CHANNEL, "duty")
    assert Rover().name == "Rover"


def test_pinout_overrides_are_merged() -> None:
    rover = Rover(pinout={"drive": {"left_pwm": 3}, "battery": {"pin": "A3"}})
    assert rover.pins.find_binder("drive.left_pwm").pin == 3
    assert rover.pins.find_binder("battery.pin").pin == 17
    assert rover.pins.find_binder("drive.right_pwm").pin == 6
    assert Rover.default_pinout["drive"]["left_pwm"] == 5  # the class default is untouched


@pytest.mark.parametrize(
    ("pinout", "culprits"),
    [
        ({"motors": {"left_pwm": 3}}, ["'motors'", "unknown device"]),
        ({"drive": {"left_pmw": 3}}, ["'left_pmw'", "'drive'", "unknown role"]),
        ({"drive": {"left_pwm": 3.5}}, ["'drive'", "'left_pwm'", "3.5"]),
        ({"drive": [3]}, ["'drive'"]),
    ],
)
def test_bad_pinout_overrides_are_named(pinout: dict, culprits: list[str]) -> None:
    with pytest.raises(VehicleError) as info:
        Rover(name="r", pinout=pinout)
    for culprit in culprits:
        assert culprit in str(info.value)
    assert "'r'" in str(info.value)


def test_override_making_a_pin_conflict_is_found_without_a_board() -> None:
    with pytest.raises(PinError) as info:
        Rover(pinout={"drive": {"left_pwm": 6}})
    assert "D6" in str(info.value) and "drive.left_pwm" in str(info.value)


def test_override_with_a_malformed_pin_names_device_and_role() -> None:
    with pytest.raises(ValueError, match=r"'drive'.*'right_fwd'"):
        Rover(pinout={"drive": {"right_fwd": "Q9"}})


def test_params_limits_state_dt() -> None:
    rover = Rover(
        params={"max_duty": 100}, limits={"left": (-50, 80)}, initial_state=[1, 2], dt=0.1
    )
    assert rover.params == {"low_v": 6.5, "max_duty": 100}
    assert rover.limits == {"left": (-50.0, 80.0), "right": (-np.inf, np.inf)}
    assert rover.initial_state.tolist() == [1.0, 2.0] and rover.dt == 0.1  # type: ignore[union-attr]


@pytest.mark.parametrize(
    ("kwargs", "culprits"),
    [
        ({"params": {"max_dutty": 3}}, ["max_dutty"]),
        ({"limits": {"up": (0, 1)}}, ["'up'"]),
        ({"limits": {"left": (1, 0)}}, ["'left'", "lo <= hi"]),
        ({"limits": {"left": 5}}, ["'left'"]),
        ({"dt": 0}, ["dt"]),
        ({"dt": float("nan")}, ["dt"]),
        ({"initial_state": [1, float("nan")]}, ["initial_state"]),
        ({"name": "a/b"}, ["a/b"]),
        ({"name": ""}, ["name"]),
    ],
)
def test_bad_configuration_is_named(kwargs: dict, culprits: list[str]) -> None:
    with pytest.raises(VehicleError) as info:
        Rover(**kwargs)
    for culprit in culprits:
        assert culprit in str(info.value)


# ---------------------------------------------------------------- definition checks
def test_missing_class_attributes_fail_at_definition() -> None:
    with pytest.raises(VehicleDefinitionError) as info:

        class NoSizes(Vehicle):
            input_names = ("a",)
            output_names = ("y",)
            default_pinout: ClassVar[dict] = {}

            def setup_devices(self) -> None: ...
            def read_outputs(self) -> list[float]:
                return [0.0]

            def actuate(self, u: np.ndarray) -> None: ...

    message = str(info.value)
    assert "NoSizes" in message and "n_inputs is missing" in message
    assert "n_outputs is missing" in message


@pytest.mark.parametrize(
    ("attrs", "culprit"),
    [
        ({"input_names": ("a", "b")}, "input_names has 2 names but n_inputs = 1"),
        ({"output_names": ("y", "y")}, "repeats"),
        ({"output_names": "y"}, "output_names must be a tuple"),
        ({"n_inputs": -1}, "n_inputs must be an int >= 0"),
        ({"n_outputs": 1.0}, "n_outputs must be an int"),
        ({"default_pinout": {"led": {"pin": 2.5}}}, "default_pinout['led']['pin'] = 2.5"),
        ({"default_pinout": {"led": 3}}, "default_pinout['led']"),
        ({"default_pinout": None}, "default_pinout must map"),
        ({"profile": "mega"}, "profile 'mega'"),
        ({"default_limits": {"b": (0, 1)}}, "default_limits names unknown input(s) ['b']"),
    ],
)
def test_inconsistent_class_attributes_fail_at_definition(attrs: dict, culprit: str) -> None:
    body = {
        "n_inputs": 1,
        "n_outputs": 1,
        "input_names": ("a",),
        "output_names": ("y",),
        "default_pinout": {},
        "setup_devices": lambda self: None,
        "read_outputs": lambda self: [0.0],
        "actuate": lambda self, u: None,
        **attrs,
    }
    with pytest.raises(VehicleDefinitionError) as info:
        type("Broken", (Vehicle,), body)
    assert culprit in str(info.value) and "Broken" in str(info.value)


def test_missing_pinout_is_fine_without_a_board() -> None:
    class Virtual(Vehicle):
        n_inputs, n_outputs = 1, 1
        input_names, output_names = ("u",), ("y",)
        needs_board = False

        def setup_devices(self) -> None: ...
        def read_outputs(self) -> list[float]:
            return [1.0]

        def actuate(self, u: np.ndarray) -> None: ...

    vehicle = Virtual()
    assert vehicle.exchange() is None
    assert vehicle.sense(0, 0.0).tolist() == [1.0]
    with pytest.raises(VehicleError, match="no board"):
        vehicle.connect(SimBoard(dt=0.1))


def test_missing_methods_fail_at_construction_with_a_clear_message() -> None:
    class Lazy(Vehicle):
        n_inputs, n_outputs = 1, 1
        input_names, output_names = ("u",), ("y",)
        default_pinout: ClassVar[dict] = {}

        def setup_devices(self) -> None: ...

    with pytest.raises(VehicleDefinitionError) as info:
        Lazy()
    message = str(info.value)
    assert "Lazy" in message and "actuate()" in message and "read_outputs()" in message
    assert "setup_devices()" not in message.split("(", maxsplit=1)[0]


def test_abstract_intermediate_base_defers_checks_to_construction() -> None:
    class PerInstance(Vehicle, abstract=True):
        needs_board = False

        def __init__(self, n: int, **kwargs: object) -> None:
            if n > 0:
                self.n_inputs = self.n_outputs = n
                self.input_names = tuple(f"u{i}" for i in range(n))
                self.output_names = tuple(f"y{i}" for i in range(n))
            super().__init__(**kwargs)  # type: ignore[arg-type]

        def setup_devices(self) -> None: ...
        def read_outputs(self) -> np.ndarray:
            return np.zeros(self.n_outputs)

        def actuate(self, u: np.ndarray) -> None: ...

    assert PerInstance(3).sense(0, 0.0).shape == (3,)
    with pytest.raises(VehicleDefinitionError, match="n_inputs is missing"):
        PerInstance(0)


def test_unused_pinout_entry_is_a_definition_error() -> None:
    class Forgetful(Rover):
        default_pinout: ClassVar = {**Rover.default_pinout, "led": {"pin": 13}}

    with pytest.raises(VehicleDefinitionError, match=r"no device.*\['led'\]"):
        Forgetful()


def test_add_device_without_pinout_is_a_definition_error() -> None:
    class NoServoPins(Rover):
        def setup_devices(self) -> None:
            super().setup_devices()
            self.add_device(Servo, "rudder")

    with pytest.raises(VehicleDefinitionError, match=r"'rudder'.*default_pinout"):
        NoServoPins()


def test_devices_assigned_as_attributes_are_collected() -> None:
    class Direct(Rover):
        default_pinout: ClassVar = {**Rover.default_pinout, "led": {"pin": 13}}

        def setup_devices(self) -> None:
            super().setup_devices()
            self.led = OutputPin(self.pins, "led", self.pinout["led"], safe_value=1)

    vehicle = Direct()
    assert vehicle.devices["led"] is vehicle.led and vehicle.led in vehicle.actuators
    vehicle.enter_safe_mode("test")
    assert vehicle.pins.staged("led.pin") == 1


# ---------------------------------------------------------------- the tick
def test_apply_limits_and_records_the_applied_input() -> None:
    rover = Rover(params={"max_duty": 200}, limits={"left": (-100, 100)})
    rover.apply([150.0, 250.0])
    # vehicle limit (left: 100), then the device range (right: 200)
    assert rover.u.tolist() == [100.0, 200.0]
    assert rover.pins.outputs[5] == 100 and rover.pins.outputs[6] == 200


@pytest.mark.parametrize(
    ("u", "culprit"),
    [
        ([1.0], r"shape \(1,\)"),
        ([[1.0, 2.0]], "shape"),
        ([1.0, float("inf")], r"u\[1\] \(right\)"),
        (["a", 1.0], "not numbers"),
    ],
)
def test_bad_inputs_are_named(u: list, culprit: str) -> None:
    with pytest.raises(VehicleError, match=culprit):
        Rover(name="r").apply(u)


def test_read_outputs_of_the_wrong_size_is_named() -> None:
    class Wrong(Rover):
        def read_outputs(self) -> list[float]:
            return [1.0, 2.0]

    board = SimBoard(dt=0.1)
    vehicle = Wrong(name="w")
    vehicle.connect(board)
    with pytest.raises(VehicleError, match=r"'w'.*shape \(2,\).*battery_v"):
        vehicle.sense(0, 0.0)


def test_actuate_returning_the_wrong_size_is_named() -> None:
    class Wrong(Rover):
        def actuate(self, u: np.ndarray) -> np.ndarray:
            super().actuate(u)
            return np.zeros(3)

    with pytest.raises(VehicleError, match=r"actuate\(\) returned shape \(3,\)"):
        Wrong().apply([0, 0])


def test_sense_before_connect_names_the_missing_exchange() -> None:
    with pytest.raises(PinError, match="exchange"):
        Rover().sense(0, 0.0)


def test_safe_mode_by_hand_stages_safe_values_without_a_board() -> None:
    rover = Rover()
    rover.apply([200, 200])
    rover.enter_safe_mode("operator")
    rover.enter_safe_mode("again")  # latched: the first reason stays
    assert rover.safe_mode_reason == "operator"
    assert set(rover.pins.outputs.values()) == {0}
    rover.apply([200, 200])
    assert set(rover.pins.outputs.values()) == {0} and rover.ignored_applies == 1


def test_connecting_a_vehicle_already_in_safe_mode_estops_the_board() -> None:
    rover = Rover()
    rover.enter_safe_mode("before connect")
    board = SimBoard(plant=DrainingBattery(), dt=0.1)
    rover.connect(board)
    assert board.estopped


def test_listener_must_be_callable() -> None:
    with pytest.raises(VehicleError, match="callable"):
        Rover().add_safe_mode_listener("no")  # type: ignore[arg-type]


# ---------------------------------------------------------------- calibration
class CalibratedRover(Rover):
    """u in m/s per wheel, through the calibration to signed duty."""

    input_names = ("v_left", "v_right")

    def actuate(self, u: np.ndarray) -> np.ndarray:
        duties = [
            self.drive.actuate(motor, self.to_pwm(name, value))
            for motor, name, value in zip(("left", "right"), self.input_names, u, strict=True)
        ]
        return np.array(
            [self.to_u(name, d) for name, d in zip(self.input_names, duties, strict=True)]
        )


CAL = Calibration(
    {
        "v_left": ([-0.2, 0.0, 0.2], [-255, 0, 255]),
        "v_right": ([-0.2, 0.0, 0.2], [-255, 0, 255]),
    }
)


def test_calibration_turns_u_into_pwm_and_back() -> None:
    rover = CalibratedRover(calibration=CAL, params={"max_duty": 200})
    rover.apply([0.1, 0.3])
    assert rover.pins.outputs[5] == 128  # 127.5 rounded
    assert rover.pins.outputs[6] == 200  # clipped by the table (0.2 -> 255), then max_duty
    assert rover.u[0] == pytest.approx(0.1, abs=0.001)
    assert rover.u[1] == pytest.approx(200 / 255 * 0.2)


def test_calibration_from_a_file(tmp_path: Path) -> None:
    path = CAL.save(tmp_path / "rover.toml")
    rover = CalibratedRover(calibration=path)
    assert rover.calibration is not None and rover.calibration.names == ("v_left", "v_right")
    assert rover.to_pwm("v_left", 0.2) == pytest.approx(255)


def test_calibration_naming_unknown_inputs_is_refused() -> None:
    with pytest.raises(CalibrationError, match="'v_left'"):
        Rover(calibration=CAL)  # Rover's inputs are left/right
    with pytest.raises(CalibrationError, match="Calibration or a file path"):
        Rover(calibration=42)  # type: ignore[arg-type]


def test_to_pwm_without_calibration_is_named() -> None:
    with pytest.raises(VehicleError, match=r"'left'.*calibration"):
        Rover().to_pwm("left", 0.1)


def test_remaining_vehicle_errors_are_named() -> None:
    with pytest.raises(VehicleError, match="params must be a mapping"):
        Rover(params=[1])  # type: ignore[arg-type]
    with pytest.raises(VehicleError, match="limits must map"):
        Rover(limits=[(0, 1)])  # type: ignore[arg-type]
    with pytest.raises(VehicleError, match="initial_state"):
        Rover(initial_state=["x"])  # type: ignore[list-item]

    class Twice(Rover):
        def setup_devices(self) -> None:
            super().setup_devices()
            self.add_device(Battery, "battery")

    with pytest.raises(VehicleError, match=r"'battery'.*twice"):
        Twice()

    class Words(Rover):
        def read_outputs(self) -> list[str]:
            return ["high"]

    vehicle = Words(name="w")
    vehicle.connect(SimBoard(plant=DrainingBattery(), dt=0.1))
    with pytest.raises(VehicleError, match=r"'w'.*not numbers"):
        vehicle.sense(0, 0.0)
    with pytest.raises(VehicleError, match=r"'left'.*calibration"):
        Rover().to_u("left", 10)
