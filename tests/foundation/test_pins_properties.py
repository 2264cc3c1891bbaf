"""Properties of the PinManager under arbitrary sequences of assign/release calls (hypothesis)."""

from __future__ import annotations

from hilswarm.agents.errors import PinError
from hilswarm.agents.link.board import PinMode
from hilswarm.agents.pins import PROFILES, PinManager
from hypothesis import given, settings
from hypothesis import strategies as st

MODES = [
    PinMode.DIGITAL_IN,
    PinMode.DIGITAL_OUT,
    PinMode.PWM,
    PinMode.SERVO,
    PinMode.ANALOG_IN,
    PinMode.DIGITAL_IN_PULLUP,
]
SAFE = {PinMode.SERVO: 1500}

assign_op = st.tuples(
    st.just("assign"),
    st.integers(min_value=-2, max_value=22),  # includes pins the board lacks and serial pins
    st.sampled_from(["a", "b", "c"]),  # device
    st.integers(min_value=0, max_value=7),  # binder suffix: repeats happen
    st.sampled_from(MODES),
)
release_op = st.tuples(
    st.just("release"),
    st.sampled_from(["binder", "device"]),
    st.sampled_from(["a", "b", "c"]),
    st.integers(min_value=0, max_value=7),
)
operations = st.lists(st.one_of(assign_op, release_op), max_size=60)


def check_invariants(pm: PinManager) -> None:
    profile = PROFILES["uno"]
    assignments = pm.assignments()
    pins = [a.pin for a in assignments]
    binders = [a.binder for a in assignments]
    # no pin held by two binders, no binder on two pins
    assert len(pins) == len(set(pins))
    assert len(binders) == len(set(binders))
    by_pin = {a.pin: a for a in assignments}
    for a in assignments:
        assert a.pin not in profile.serial_pins
        assert pm.find_binder(a.binder) == a
        if a.mode is PinMode.PWM:
            assert a.pin in profile.pwm_pins
        if a.mode is PinMode.SERVO:
            assert a.pin in profile.servo_pins
            partner = profile.timer1_partner(a.pin)
            # never PWM on the Timer1 partner of a servo pin
            assert partner is None or partner not in by_pin or by_pin[partner].mode != PinMode.PWM
    assert pm.used_pins() == sorted(pins)


@settings(max_examples=300, deadline=None)
@given(operations)
def test_no_pin_ever_has_two_binders_and_no_pwm_beside_a_servo(ops: list[tuple]) -> None:
    pm = PinManager("uno")
    for op in ops:
        try:
            if op[0] == "assign":
                _, pin, device, suffix, mode = op
                pm.assign(
                    pin,
                    device=device,
                    binder=f"{device}.{suffix}",
                    mode=mode,
                    safe_value=SAFE.get(mode, 0),
                )
            elif op[1] == "binder":
                pm.release(binder=f"{op[2]}.{op[3]}")
            else:
                pm.release(device=op[2])
        except PinError:
            pass  # refused requests must leave the manager unchanged and consistent
        check_invariants(pm)


@settings(max_examples=200, deadline=None)
@given(operations)
def test_a_refused_request_changes_nothing(ops: list[tuple]) -> None:
    pm = PinManager("uno")
    for op in ops:
        before = pm.assignments()
        try:
            if op[0] == "assign":
                _, pin, device, suffix, mode = op
                pm.assign(
                    pin,
                    device=device,
                    binder=f"{device}.{suffix}",
                    mode=mode,
                    safe_value=SAFE.get(mode, 0),
                )
            elif op[1] == "binder":
                pm.release(binder=f"{op[2]}.{op[3]}")
            else:
                pm.release(device=op[2])
        except PinError:
            assert pm.assignments() == before
