"""The ten-line vehicle of docs/vehicles.md runs as documented (the doc's code is executed)."""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from hilswarm.agents.devices import Battery, HBridgeMotor
from hilswarm.agents.errors import PinError, VehicleError
from hilswarm.agents.link.board import BoardStatus
from hilswarm.agents.link.sim_board import SimBoard
from hilswarm.agents.vehicle import Vehicle

DOC = Path(__file__).resolve().parents[2] / "docs" / "vehicles.md"


def snippet(marker: str) -> str:
    match = re.search(rf"<!-- {marker} -->\s*```python\n(.*?)```", DOC.read_text(), re.DOTALL)
    assert match is not None, f"docs/vehicles.md lost the {marker} block"
    return match.group(1)


def define_cart() -> type[Vehicle]:
    namespace: dict[str, Any] = {}
    exec(compile(snippet("vehicle-example"), str(DOC), "exec"), namespace)
    return namespace["Cart"]


def test_the_example_is_about_ten_lines() -> None:
    code = snippet("vehicle-example")
    body = code[code.index("class Cart") :]
    lines = [line for line in body.splitlines() if line.strip()]
    assert len(lines) <= 11  # the class statement + ten lines


def test_the_documented_usage_runs() -> None:
    namespace: dict[str, Any] = {}
    exec(compile(snippet("vehicle-example"), str(DOC), "exec"), namespace)
    exec(compile(snippet("vehicle-usage"), str(DOC), "exec"), namespace)
    cart = namespace["cart"]
    assert cart.pins.find_binder("battery.pin").pin == 15  # the override moved it to A1
    assert cart.u.tolist() == [200.0, -120.0]  # left clipped by the vehicle limit
    assert namespace["y"].shape == (1,)


def test_the_example_is_the_vehicle_it_claims_to_be() -> None:
    cart_class = define_cart()
    cart = cart_class(name="cart")
    assert isinstance(cart.drive, HBridgeMotor) and isinstance(cart.battery, Battery)
    assert cart.pins.used_pins() == [4, 5, 6, 7, 8, 12, 14]
    with pytest.raises(VehicleError, match="left_pmw"):
        cart_class(pinout={"drive": {"left_pmw": 3}})
    with pytest.raises(PinError, match=r"drive\.right_pwm"):
        cart_class(pinout={"drive": {"left_pwm": 6}})


class FlatBattery:
    """A pack at 7 V through the 1:3 divider, losing 1 V per second of full duty."""

    def __init__(self) -> None:
        self.volts = 7.0

    def advance(self, outputs: dict[int, int], dt: float) -> dict[int, float]:
        self.volts -= (outputs.get(5, 0) + outputs.get(6, 0)) / 510 * dt
        return {14: self.volts / 3}

    def pose(self) -> np.ndarray:
        return np.zeros(6)


def test_the_example_goes_safe_on_low_battery() -> None:
    cart = define_cart()(name="cart")
    board = SimBoard(plant=FlatBattery(), dt=0.1)
    cart.connect(board)
    for k in range(100):
        cart.sense(k, k * 0.1)
        cart.apply([255, 255])
        cart.exchange()
        if cart.safe_mode:
            break
    assert cart.safe_mode and "low battery" in str(cart.safe_mode_reason)
    assert set(board.outputs.values()) == {0} and board.status & BoardStatus.ESTOPPED
