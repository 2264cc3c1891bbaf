"""Channel / Telemetry: growable storage, exports, errors, MCAP export."""

from __future__ import annotations

import numpy as np
import pytest
from hilswarm.agents.errors import HilswarmError, TelemetryError
from hilswarm.agents.mcap_io import McapJsonWriter, iter_messages
from hilswarm.agents.telemetry import Channel, Telemetry, telemetry_topic, write_to_mcap
from hypothesis import given, settings
from hypothesis import strategies as st


def test_append_and_export_round_trip() -> None:
    channel = Channel("position", ("x", "y", "z"), initial_capacity=2)
    rows = np.arange(30, dtype=float).reshape(10, 3)
    for k, row in enumerate(rows):
        channel.append(k, 0.1 * k, row)
    k, t, values = channel.arrays()
    assert len(channel) == 10
    np.testing.assert_array_equal(k, np.arange(10))
    np.testing.assert_allclose(t, 0.1 * np.arange(10))
    np.testing.assert_array_equal(values, rows)
    assert k.dtype == np.int64 and values.shape == (10, 3)
    np.testing.assert_array_equal(channel.field("y"), rows[:, 1])
    assert channel.last() == (9, pytest.approx(0.9), pytest.approx(rows[9]))


def test_capacity_doubles() -> None:
    channel = Channel("c", ("v",), initial_capacity=1)
    capacities = []
    for i in range(9):
        channel.append(i, float(i), i)
        capacities.append(channel.capacity)
    assert capacities == [1, 2, 4, 4, 8, 8, 8, 8, 16]


def test_copies_are_independent_and_views_read_only() -> None:
    channel = Channel("c", ("a", "b"))
    channel.append(0, 0.0, [1.0, 2.0])
    copied = channel.arrays()
    copied.values[0, 0] = 99.0
    assert channel.arrays().values[0, 0] == 1.0
    view = channel.arrays(copy=False)
    with pytest.raises(ValueError):
        view.values[0, 0] = 5.0
    channel.append(1, 0.1, [3.0, 4.0])
    assert len(view.k) == 1  # a view is the filled part at the time it was taken


def test_nan_is_kept() -> None:
    channel = Channel("c", ("a",))
    channel.append(0, 0.0, [np.nan])
    assert np.isnan(channel.arrays().values[0, 0])


@pytest.mark.parametrize("values", [[1.0], [1.0, 2.0, 3.0], [[1.0, 2.0]], "ab"])
def test_wrong_length_names_channel_and_fields(values: object) -> None:
    channel = Channel("battery", ("v", "i"))
    with pytest.raises(TelemetryError, match=r"battery.*2 values.*\('v', 'i'\)"):
        channel.append(0, 0.0, values)  # type: ignore[arg-type]
    assert len(channel) == 0


def test_scalar_for_single_field() -> None:
    channel = Channel("v", ("volts",))
    channel.append(3, 0.3, 7.5)
    assert channel.last() == (3, 0.3, pytest.approx([7.5]))


@pytest.mark.parametrize(
    ("name", "fields"),
    [("", ("a",)), ("a/b", ("a",)), ("ok", ()), ("ok", "xy"), ("ok", ("a", "a")), ("ok", ("",))],
)
def test_bad_definitions(name: str, fields: tuple[str, ...]) -> None:
    with pytest.raises(TelemetryError):
        Channel(name, fields)


def test_telemetry_errors_are_value_errors() -> None:
    assert issubclass(TelemetryError, HilswarmError) and issubclass(TelemetryError, ValueError)


def test_telemetry_by_name_and_iteration() -> None:
    telemetry = Telemetry()
    pos = telemetry.add_channel("pos", ("x", "y"))
    bat = telemetry.add_channel("battery", ("v",))
    assert telemetry["pos"] is pos and "battery" in telemetry and "nope" not in telemetry
    assert [c.name for c in telemetry] == ["pos", "battery"] == list(telemetry.names)
    assert len(telemetry) == 2
    with pytest.raises(TelemetryError, match="exists already"):
        telemetry.add_channel("pos", ("z",))
    with pytest.raises(TelemetryError, match=r"no telemetry channel 'nope'.*pos"):
        telemetry["nope"]
    pos.append(0, 0.0, [1, 2])
    bat.append(0, 0.0, 4.0)
    telemetry.clear()
    assert len(pos) == 0 and len(bat) == 0


def test_write_to_mcap(tmp_path) -> None:
    telemetry = Telemetry()
    pos = telemetry.add_channel("pos", ("x", "y"))
    telemetry.add_channel("empty", ("v",))
    for k in range(5):
        pos.append(k, 0.5 * k, [k, np.nan if k == 2 else -k])
    path = tmp_path / "t.mcap"
    with McapJsonWriter(path) as writer:
        assert write_to_mcap(telemetry, writer, "robot1", start_time_ns=1000) == 5
        assert telemetry.write_to_mcap(writer, "robot2") == 5
    messages = list(iter_messages(path, topics=[telemetry_topic("robot1", "pos")]))
    assert [m[0] for m in messages] == ["/robot1/telemetry/pos"] * 5
    assert [m[1] for m in messages] == [1000 + 500_000_000 * k for k in range(5)]
    third = messages[2][2]
    assert third == {"k": 2, "t": 1.0, "values": [2.0, None], "x": 2.0, "y": None}
    with McapJsonWriter(tmp_path / "u.mcap") as writer, pytest.raises(TelemetryError):
        write_to_mcap(telemetry, writer, "a/b")


@settings(max_examples=50, deadline=None)
@given(
    st.lists(
        st.lists(st.floats(allow_nan=False, width=64), min_size=3, max_size=3),
        max_size=200,
    ),
    st.integers(min_value=1, max_value=8),
)
def test_matches_a_plain_list(rows: list[list[float]], capacity: int) -> None:
    channel = Channel("c", ("a", "b", "c"), initial_capacity=capacity)
    for k, row in enumerate(rows):
        channel.append(k, float(k), row)
    expected = np.array(rows, dtype=float).reshape(-1, 3)
    np.testing.assert_array_equal(channel.arrays().values, expected)
    assert channel.capacity >= len(rows)
    assert channel.capacity < max(capacity, 2 * len(rows)) + 1
