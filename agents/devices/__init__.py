"""Devices: actuators, sensors and in/out devices bound to board pins through the PinManager."""
