"""The per-tick fast paths give exactly what the full paths give, and refuse exactly as much.

Every fast path (SimBoard TICK checks, PinManager writes, scalar calibration, the float arc
step, the cached waypoint parse) must be an optimisation only: same values bit for bit, and
every request the full checks refuse still refused with the same error code and pin.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from hilswarm.agents.calibration import Calibration
from hilswarm.agents.control import ControlModel, TickInput
from hilswarm.agents.controllers.waypoint import WaypointController
from hilswarm.agents.errors import BoardRequestError, PinError
from hilswarm.agents.link.board import PinConfig, PinMode
from hilswarm.agents.link.sim_board import SimBoard
from hilswarm.agents.pins import PinManager
from hilswarm.agents.sim.differential_drive import DifferentialDrive
from hilswarm.agents.vehicles.frisbee import DEFAULT_CALIBRATION
from hypothesis import given, settings
from hypothesis import strategies as st

CONFIG = [
    PinConfig(4, PinMode.DIGITAL_OUT),
    PinConfig(5, PinMode.PWM),
    PinConfig(9, PinMode.SERVO, 1500),
    PinConfig(12, PinMode.DIGITAL_IN),
    PinConfig(14, PinMode.ANALOG_IN),
]

pins = st.one_of(
    st.sampled_from([4, 5, 9, 12, 14]),  # configured: most requests pass the checks
    st.integers(-2, 22),
    st.sampled_from([True, False, np.int64(5), 5.0, "5", None]),
)
values = st.one_of(
    st.integers(0, 1),
    st.integers(400, 2600),
    st.integers(-5, 2600),
    st.sampled_from([True, False, np.int64(1), np.uint8(200), 1.0, 1.5, math.nan, "1", None]),
)


def configured() -> SimBoard:
    board = SimBoard(dt=0.01)
    board.open()
    board.configure(CONFIG, watchdog_s=0.0)
    return board


def outcome(board: SimBoard, writes: dict, reads: list) -> tuple:
    """What the full checks say: ("ok", writes, reads) or ("refused", code, pin)."""
    try:
        checked, read_pins = board._tick_checks(writes, reads)
    except BoardRequestError as exc:
        return ("refused", exc.code, exc.pin)
    return ("ok", dict(checked), list(read_pins))


@settings(max_examples=400, deadline=None)
@given(
    writes=st.dictionaries(pins, values, max_size=5),
    reads=st.lists(pins, max_size=4),
)
def test_simboard_fast_checks_accept_only_what_the_full_checks_accept(
    writes: dict, reads: list
) -> None:
    board = configured()
    try:
        fast = board._tick_fast_checks(writes, reads)
    except TypeError:  # unhashable or unorderable junk: the full checks decide
        fast = None
    full = outcome(board, writes, reads)
    if fast is not None:
        assert full == ("ok", dict(fast[0]), list(fast[1]))


valid_writes = st.fixed_dictionaries(
    {},
    optional={4: st.integers(0, 1), 5: st.integers(0, 255), 9: st.integers(500, 2500)},
)
valid_reads = st.lists(st.sampled_from([12, 14]), unique=True)


@settings(max_examples=200, deadline=None)
@given(writes=valid_writes, reads=valid_reads)
def test_simboard_fast_checks_take_every_valid_request(writes: dict, reads: list) -> None:
    board = configured()
    fast = board._tick_fast_checks(writes, reads)
    assert fast is not None
    assert outcome(board, writes, reads) == ("ok", dict(fast[0]), list(fast[1]))


@settings(max_examples=300, deadline=None)
@given(
    writes=st.one_of(valid_writes, st.dictionaries(pins, values, max_size=5)),
    reads=st.one_of(valid_reads, st.lists(pins, max_size=4)),
)
def test_simboard_exchange_refuses_like_the_full_checks(writes: dict, reads: list) -> None:
    board = configured()
    full = outcome(board, writes, reads)
    if full[0] == "ok":
        reply = board.exchange(writes, reads)
        assert sorted(reply.samples) == full[2]
        for pin, value in full[1].items():
            assert board.outputs[pin] == value
    else:
        with pytest.raises(BoardRequestError) as info:
            board.exchange(writes, reads)
        assert (info.value.code, info.value.pin) == full[1:]


@settings(max_examples=300, deadline=None)
@given(
    binder=st.sampled_from(["led.pin", "motor.pwm", "servo.pin", "switch.pin", "nope"]),
    value=values,
)
def test_pin_manager_write_fast_path_refuses_like_the_full_checks(
    binder: str, value: object
) -> None:
    manager = PinManager("uno")
    manager.assign(4, device="led", binder="led.pin", mode=PinMode.DIGITAL_OUT)
    manager.assign(5, device="motor", binder="motor.pwm", mode=PinMode.PWM)
    manager.assign(9, device="servo", binder="servo.pin", mode=PinMode.SERVO, safe_value=1500)
    manager.assign(12, device="switch", binder="switch.pin", mode=PinMode.DIGITAL_IN)
    reference = PinManager("uno")
    for assignment in manager.assignments():
        reference.assign(
            assignment.pin,
            device=assignment.device,
            binder=assignment.binder,
            mode=assignment.mode,
            safe_value=assignment.safe_value,
        )
    reference._output_specs.clear()  # the reference takes the full checks every time
    reference._input_pins.clear()
    results = []
    for pm in (manager, reference):
        try:
            pm.write(binder, value)  # type: ignore[arg-type]
            results.append(("ok", pm.outputs))
        except PinError as exc:
            results.append(("refused", str(exc)))
    assert results[0] == results[1]


def test_pin_manager_still_notices_a_changed_layout() -> None:
    board = SimBoard(dt=0.01)
    manager = PinManager("uno")
    manager.assign(5, device="motor", binder="motor.pwm", mode=PinMode.PWM)
    manager.attach(board, watchdog_s=0.0)
    manager.exchange()
    manager.assign(6, device="other", binder="other.pwm", mode=PinMode.PWM)
    with pytest.raises(PinError, match="changed since attach"):
        manager.exchange()
    manager.release(device="other")  # back to the configured layout: accepted again
    manager.exchange()


@pytest.fixture(scope="module")
def calibration() -> Calibration:
    return Calibration.from_file(DEFAULT_CALIBRATION)


@settings(max_examples=300, deadline=None)
@given(u=st.floats(-0.3, 0.3), duty=st.integers(-255, 255))
def test_scalar_calibration_is_bit_exact(calibration: Calibration, u: float, duty: int) -> None:
    for name in calibration.names:
        curve = calibration.curve(name)
        lo, hi = curve.u_range
        inside = min(max(u, lo), hi)
        assert curve.pwm_at_scalar(inside) == float(curve.pwm_at(np.array([inside]))[0])
        assert calibration.to_pwm(name, u) == float(calibration.to_pwm(name, np.array(u)))
        low, high = curve.pwm_range
        if low <= duty <= high:
            expected = float(curve.u_at(np.array([float(duty)]))[0])
            assert curve.u_at_scalar(float(duty)) == expected
            assert calibration.to_u(name, duty) == expected


def test_prepared_inverse_matches_the_root_search(calibration: Calibration) -> None:
    fresh = Calibration.from_file(DEFAULT_CALIBRATION)
    fresh.prepare_inverse()
    for name in fresh.names:
        curve = fresh.curve(name)
        low, high = curve.pwm_range
        duties = np.arange(math.ceil(low), math.floor(high) + 1, dtype=float)
        assert len(curve._inverse_cache) == duties.size
        np.testing.assert_array_equal(
            [curve.u_at_scalar(d) for d in duties], calibration.curve(name).u_at(duties)
        )


@settings(max_examples=300, deadline=None)
@given(
    state=st.tuples(st.floats(-5, 5), st.floats(-5, 5), st.floats(-10, 10)),
    wheels=st.tuples(st.floats(-0.5, 0.5), st.floats(-0.5, 0.5)),
    dt=st.sampled_from([0.0, 0.001, 0.01, 0.05]),
)
def test_float_arc_step_equals_the_array_step(
    state: tuple[float, float, float], wheels: tuple[float, float], dt: float
) -> None:
    drive = DifferentialDrive()
    expected = drive.step(np.array(state), np.array(wheels), dt)
    np.testing.assert_array_equal(np.array(drive.step_floats(state, wheels, dt=dt)), expected)


def test_waypoint_parse_is_cached_only_for_validated_tuples() -> None:
    controller = WaypointController()
    params = controller.validate_params({"waypoints": [[1.0, 0.0], [1.0, 1.0]]})
    assert params["waypoints"] == ((1.0, 0.0), (1.0, 1.0))
    tick = TickInput(0, 0.0, 0.1, np.zeros(2), np.zeros(3))
    x_hat = controller.initial_state(params)
    first = controller.step(tick, x_hat, params)
    assert controller._route_cache is not None
    assert controller._route_cache[0] is params["waypoints"]
    # A mutable list passed straight to step() is parsed again on every call.
    raw = dict(params, waypoints=[[1.0, 0.0], [1.0, 1.0]])
    again = controller.step(tick, x_hat, raw)
    np.testing.assert_array_equal(first[0], again[0])
    raw["waypoints"][0][0] = 2.0
    controller.step(tick, x_hat, raw)
    assert controller._route(raw["waypoints"])[0] == (2.0, 0.0)  # the change was seen


def test_control_model_neither_copies_nor_exposes_read_only_inputs() -> None:
    seen: list[TickInput] = []

    class Spy(WaypointController):
        def step(self, tick, x_hat, params):  # type: ignore[no-untyped-def]
            seen.append(tick)
            return super().step(tick, x_hat, params)

    model = ControlModel(Spy(), dt=0.1, n_inputs=2, n_outputs=3)
    neighbour = np.array([1.0, 2.0, 3.0])
    neighbour.flags.writeable = False
    u = model.step(np.zeros(2), np.zeros(3), neighbours={"n": neighbour, "gone": None})
    tick = seen[-1]
    assert tick.neighbours["n"] is neighbour  # read-only and owned: no copy needed
    assert tick.neighbours["gone"] is None
    assert not tick.u.flags.writeable and not tick.y.flags.writeable
    assert u.flags.writeable  # the caller's own array
    with pytest.raises(TypeError):
        tick.neighbours["x"] = None  # type: ignore[index]
