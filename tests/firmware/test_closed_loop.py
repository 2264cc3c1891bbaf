"""Closed loop around the real firmware: a vehicle on simavr:// behaves like the same on sim://.

A small vehicle (an H-bridge motor and a speed sensor read on A0) drives a first-order motor
model; the model's speed comes back as an analog voltage. A proportional speed controller closes
the loop. The run on the simulated firmware (``simavr://uno``, bytes through a pty) and the run
on the in-process board (``sim://uno``) must agree within the ADC quantisation.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import ClassVar

import numpy as np
import pytest
from hilswarm.agents.devices.battery import Battery
from hilswarm.agents.devices.hbridge_motor import HBridgeMotor
from hilswarm.agents.link.board import Board
from hilswarm.agents.link.sim_board import SimBoard
from hilswarm.agents.link.simavr import SimavrBoard
from hilswarm.agents.vehicle import Vehicle

pytestmark = pytest.mark.firmware

DT_S = 0.02
TICKS = 60
VREF_V = 5.0
LSB_V = VREF_V / 1023


class FirstOrderMotor:
    """Motor speed ``w`` [rad/s]: ``dw/dt = (gain * duty/255 - w) / tau``.

    Sensor voltage = 2.5 V + 0.1 V·s/rad · w.

    Pins: direction D7 (forward), D8 (backward), duty D5 (PWM); sensor voltage on A0 [V].
    """

    def __init__(self, *, gain: float = 20.0, tau_s: float = 0.15) -> None:
        self.gain = gain
        self.tau_s = tau_s
        self.speed = 0.0

    def advance(self, outputs: Mapping[int, int], dt: float) -> Mapping[int, float]:
        """Hold ``outputs`` for ``dt`` [s] (exact exponential step); return {A0: volts}."""
        direction = outputs.get(7, 0) - outputs.get(8, 0)
        target = self.gain * direction * outputs.get(5, 0) / 255.0
        self.speed = target + (self.speed - target) * np.exp(-dt / self.tau_s)
        return {14: min(max(2.5 + 0.1 * self.speed, 0.0), VREF_V)}

    def pose(self) -> np.ndarray:
        """No pose: the motor sits still on the bench."""
        return np.zeros(6)


class BenchMotor(Vehicle):
    """One H-bridge motor; output: the speed sensor voltage [V]; input: signed duty [-255, 255]."""

    n_inputs = 1
    n_outputs = 1
    input_names = ("duty",)
    output_names = ("sensor_v",)
    default_pinout: ClassVar[Mapping[str, Mapping[str, int | str]]] = {
        "drive": {"m_fwd": 7, "m_back": 8, "m_pwm": 5},
        "sensor": {"pin": "A0"},
    }

    def setup_devices(self) -> None:
        self.drive = self.add_device(HBridgeMotor, "drive", motors=("m",))
        self.sensor = self.add_device(Battery, "sensor")

    def read_outputs(self) -> np.ndarray:
        return np.array([self.sensor.sense()])

    def actuate(self, u: np.ndarray) -> None:
        self.drive.actuate("m", float(u[0]))


def speed_controller(y_v: float, reference_v: float) -> np.ndarray:
    """Proportional control of the sensor voltage [V] -> signed duty."""
    return np.array([float(np.clip(400.0 * (reference_v - y_v), -255, 255))])


def run(board: Board) -> tuple[np.ndarray, np.ndarray]:
    """Run the loop for TICKS ticks; return (y [V], u [duty]) per tick."""
    vehicle = BenchMotor(name="bench", dt=DT_S)
    ys, us = [], []
    vehicle.connect(board, watchdog_s=0)
    for k in range(TICKS):
        y = vehicle.sense(k, k * DT_S)
        reference_v = 3.5 if k < TICKS // 2 else 1.8
        u = speed_controller(float(y[0]), reference_v)
        vehicle.apply(u)
        vehicle.exchange()
        ys.append(float(y[0]))
        us.append(float(vehicle.u[0]))
    return np.array(ys), np.array(us)


def test_vehicle_on_simavr_matches_sim(firmware_built: Path) -> None:
    with SimBoard("uno", plant=FirstOrderMotor(), dt=DT_S) as sim_board:
        y_sim, u_sim = run(sim_board)
    with SimavrBoard("uno", plant=FirstOrderMotor(), dt=DT_S, timeout_s=0.5) as avr_board:
        y_avr, u_avr = run(avr_board)
    # The loop did something: it settled near both references (a P controller keeps an offset).
    assert abs(y_sim[TICKS // 2 - 1] - 3.5) < 0.4 and abs(y_sim[-1] - 1.8) < 0.4
    assert np.ptp(u_sim) > 200
    # Same behaviour within the ADC quantisation (a few LSB after the feedback).
    print("max |y_sim - y_avr| =", np.abs(y_sim - y_avr).max() / LSB_V, "LSB")
    assert np.max(np.abs(y_sim - y_avr)) <= 3 * LSB_V
    assert np.max(np.abs(u_sim - u_avr)) <= 400.0 * 3 * LSB_V + 1
