"""The Blimpduino vehicle: Code Sample A.2 pinout, PinManager rules, safe mode on a SimBoard."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hilswarm.agents.control import ControlModel
from hilswarm.agents.controllers.blimp_flight import BlimpFlightController
from hilswarm.agents.errors import PinError, VehicleError
from hilswarm.agents.link.board import PinMode
from hilswarm.agents.link.sim_board import SimBoard
from hilswarm.agents.registry import resolve_vehicle
from hilswarm.agents.sim.blimp import BlimpPinPlant
from hilswarm.agents.sim.blimp_params import DEFAULT_BLIMP_PARAMS
from hilswarm.agents.vehicles.blimpduino import (
    Blimpduino,
    reference_calibration,
    reference_thrust,
)

P = DEFAULT_BLIMP_PARAMS
DT = 0.05
NEUTRAL_US = (P.servo_min_us + P.servo_max_us) // 2


def connected(**params) -> tuple[Blimpduino, SimBoard, BlimpPinPlant]:
    vehicle = Blimpduino(name="blimp", dt=DT, params=params or None)
    plant = vehicle.simulated_hardware(initial_state=[0.0, 0.0, -1.0, 0.0], dt=DT)
    board = SimBoard("fio", plant=plant, dt=DT)
    vehicle.pose_source = plant
    vehicle.connect(board, watchdog_s=0.5)
    return vehicle, board, plant


def test_registry_name_and_declarations() -> None:
    assert resolve_vehicle("blimpduino") is Blimpduino
    assert Blimpduino.profile == "fio"
    assert Blimpduino.input_names == ("thrust_left", "thrust_right", "thrust_angle")
    assert Blimpduino.output_names == ("x", "y", "z", "yaw")


def test_pinout_is_code_sample_a2() -> None:
    vehicle = Blimpduino()
    motor = vehicle.pins.find_device("motor")
    assert motor == {
        "motor.left_fwd": 5,
        "motor.left_back": 4,
        "motor.left_pwm": 3,
        "motor.right_fwd": 7,
        "motor.right_back": 8,
        "motor.right_pwm": 11,
    }
    assert vehicle.pins.find_device("servo") == {"servo.pin": 10}
    assert vehicle.pins.find_device("standby") == {"standby.pin": 6}
    assert vehicle.pins.find_device("battery") == {"battery.pin": 14}  # A0
    modes = {config.pin: config.mode for config in vehicle.pins.pin_configs()}
    assert modes[3] == modes[11] == PinMode.PWM
    assert modes[10] == PinMode.SERVO
    assert modes[14] == PinMode.ANALOG_IN
    assert all(modes[pin] == PinMode.DIGITAL_OUT for pin in (4, 5, 6, 7, 8))
    # The H-bridge standby pin is driven HIGH from the start (Code Sample A.2, line 44).
    assert vehicle.pins.outputs[6] == 1
    battery = vehicle.battery
    assert (battery.vref_v, battery.multiplier, battery.low_v) == (3.3, 3.0, 6.5)


def test_servo_on_10_takes_pwm_away_from_9() -> None:
    vehicle = Blimpduino()
    with pytest.raises(PinError, match="9"):
        vehicle.pins.assign(9, device="extra", binder="extra.pwm", mode=PinMode.PWM)
    # A pinout override that moves a motor's PWM to pin 9 is refused on construction.
    with pytest.raises(PinError, match="9"):
        Blimpduino(pinout={"motor": {"left_pwm": 9}})
    # Moving the servo to 9 frees 10 for PWM but then 9's partner (10) cannot carry PWM.
    with pytest.raises(PinError, match="10"):
        Blimpduino(pinout={"servo": {"pin": 9}, "motor": {"right_pwm": 10}})


def test_two_devices_on_one_pin_are_refused() -> None:
    with pytest.raises(PinError, match="6"):
        Blimpduino(pinout={"motor": {"left_fwd": 6}})


def test_actuate_converts_through_calibration_and_servo() -> None:
    vehicle, board, plant = connected()
    vehicle.apply([0.03, -0.0637, -math.pi / 2])
    vehicle.exchange()
    outputs = board.outputs
    calibration = reference_calibration()
    left = round(calibration.to_pwm("thrust_left", 0.03))
    assert (outputs[5], outputs[4], outputs[3]) == (1, 0, left)
    assert (outputs[7], outputs[8], outputs[11]) == (0, 1, 255)
    assert outputs[10] == NEUTRAL_US
    assert outputs[6] == 1
    # The applied input is what the quantised duty really gives.
    assert vehicle.u[0] == pytest.approx(float(reference_thrust(left)), rel=1e-3)
    assert vehicle.u[1] == pytest.approx(-P.thrust_limit_n)
    np.testing.assert_allclose(plant.inputs, vehicle.u, atol=1e-9)


def test_limits_clip_thrust_and_thrust_angle() -> None:
    vehicle, board, _ = connected()
    vehicle.apply([1.0, -1.0, 1.0])
    np.testing.assert_allclose(vehicle.u, [P.thrust_limit_n, -P.thrust_limit_n, 0.0])
    vehicle.exchange()
    assert board.outputs[10] == P.servo_max_us


def test_outputs_come_from_the_pose_source() -> None:
    vehicle, _, plant = connected()
    y = vehicle.sense(0, 0.0)
    np.testing.assert_allclose(y, plant.pose()[[0, 1, 2, 5]])
    lonely = Blimpduino()
    with pytest.raises(VehicleError, match="pose source"):
        lonely.sense(0, 0.0)


def test_low_battery_puts_the_blimp_in_safe_mode() -> None:
    # 2 % charge: the 2S LiPo reads below 6.5 V on A0 (through the 1:3 divider, 3.3 V ref).
    vehicle, board, plant = connected(battery_charge=0.02)
    vehicle.apply([0.05, 0.05, 0.0])
    vehicle.exchange()
    assert plant.battery.volts < 6.5
    vehicle.sense(1, DT)
    assert vehicle.safe_mode
    assert "low battery" in (vehicle.safe_mode_reason or "")
    assert board.estopped
    outputs = board.outputs
    assert outputs[3] == outputs[11] == 0  # motors off
    assert outputs[4] == outputs[5] == outputs[7] == outputs[8] == 0
    assert outputs[6] == 0  # H-bridge disabled
    assert outputs[10] == NEUTRAL_US  # servo neutral
    np.testing.assert_allclose(vehicle.u, [0.0, 0.0, -math.pi / 2])
    # Commands are ignored from now on; the plant gets no thrust.
    vehicle.apply([0.06, 0.06, 0.0])
    vehicle.exchange()
    np.testing.assert_allclose(plant.inputs[:2], 0.0)
    assert vehicle.ignored_applies == 1


def test_healthy_battery_flies_a_closed_loop_on_the_board() -> None:
    vehicle, board, plant = connected()
    model = ControlModel(
        BlimpFlightController(),
        dt=DT,
        n_inputs=3,
        n_outputs=4,
        params={
            "waypoint": [0.0, 0.0, -1.5],
            "schedule_airspeeds": (0.0, 0.1, 0.3),
            "schedule_headings": 4,
        },
    )
    for k in range(300):
        y = vehicle.sense(k, k * DT)
        vehicle.apply(model.step(vehicle.u, y, t=k * DT))
        vehicle.exchange()
    assert not vehicle.safe_mode
    assert plant.pose()[2] == pytest.approx(-1.5, abs=0.06)
    assert board.outputs[6] == 1
    assert 7.4 < plant.battery.volts < 8.4
    duty = vehicle.telemetry["duty"].arrays().values
    assert duty.shape == (300, 2)


def test_bad_vehicle_parameters_are_refused() -> None:
    with pytest.raises(VehicleError, match="battery_charge"):
        Blimpduino(params={"battery_charge": 2.0})
    with pytest.raises(VehicleError, match="substeps"):
        Blimpduino(params={"substeps": 0})
