"""Devices: actuators, sensors and in/out devices bound to board pins through the PinManager."""

from hilswarm.agents.devices.base import Actuator, Device, InOut, Sensor
from hilswarm.agents.devices.battery import Battery, LowBatteryEvent
from hilswarm.agents.devices.hbridge_motor import HBridgeMotor
from hilswarm.agents.devices.output_pin import OutputPin
from hilswarm.agents.devices.servo import Servo

__all__ = [
    "Actuator",
    "Battery",
    "Device",
    "HBridgeMotor",
    "InOut",
    "LowBatteryEvent",
    "OutputPin",
    "Sensor",
    "Servo",
]
