"""``hilswarm replay`` on real runs: every demo in graphs/ replays bit-exact; a change diverges."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest
from hilswarm.agents.mcap_io import iter_messages
from hilswarm.orchestrator import replay

GRAPHS = Path(__file__).resolve().parents[2] / "graphs"
DEMOS = sorted(p.name for p in GRAPHS.glob("*.toml"))
RUN_TIMEOUT_S = 180


def hilswarm(*args: str, timeout_s: float = RUN_TIMEOUT_S) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "hilswarm.orchestrator.cli", *args],
        capture_output=True, text=True, timeout=timeout_s, check=False,
    )  # fmt: skip


def record(demo: str, out: Path, duration_s: float = 1.0) -> Path:
    result = hilswarm(
        "run", str(GRAPHS / demo), "--duration", str(duration_s), "--out", str(out),
    )  # fmt: skip
    assert out.is_file(), result.stdout + result.stderr
    return out


@pytest.fixture(scope="module")
def lead_follow(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return record("lead_follow.toml", tmp_path_factory.mktemp("replay") / "lf.mcap", 2.0)


def first_irregular_ticks(path: Path, recording: replay.Recording) -> dict[str, int | None]:
    """Realtime: per agent, the first tick whose inputs the recording does not pin down
    (``None``: none), after which an unchanged replay need not be bit-exact.

    At tick ``k`` an agent uses its own last output and each neighbour's ``y_{k-1}``. That is
    what the file holds unless the agent skipped tick ``k - 1`` (it fell behind: no ``y_{k-1}``
    of its own, and it may have used a neighbour's older output), or a neighbour was late for
    tick ``k - 1`` or lost (listed missing in tick ``k``: the agent used ``None`` unless that
    ``y_{k-1}`` had reached it anyway, which the file does not say), or a neighbour's
    ``y_{k-1}`` is not in the file.
    """
    ticks = {m["k"]: m for _, _, m in iter_messages(path, ["/orchestrator/ticks"])}
    first: dict[str, int | None] = {}
    for name, trace in recording.traces.items():
        first[name] = None
        for k in sorted(trace.u):
            account = ticks.get(k - 1)
            if account is None or (k - 1) not in trace.y:
                first[name] = k
                break
            missing = {*account["late"], *account["missing"], *ticks.get(k, {}).get("missing", ())}
            if any(
                j in missing or (k - 1) not in recording.traces.get(j, replay.AgentTrace()).y
                for j in recording.neighbours(name)
            ):
                first[name] = k
                break
    return first


@pytest.mark.parametrize("demo", DEMOS)
def test_unchanged_replay_of_every_demo_is_bit_exact(demo: str, tmp_path: Path) -> None:
    """Lockstep: bit-exact on every tick. Realtime (docs/recording.md, Replay): bit-exact on
    every tick before an agent's first tick whose inputs the recording does not pin down (a
    tick it skipped, a late or lost neighbour), and on all of them when there is none."""
    checked = hilswarm("check", str(GRAPHS / demo))
    assert checked.returncode == 0, f"{demo} fails check:\n{checked.stdout}{checked.stderr}"
    path = record(demo, tmp_path / "run.mcap")
    recording = replay.load_recording(path)
    results = replay.replay(recording, search_path=GRAPHS)
    assert results, f"{demo}: no agent replayed"
    assert sum(r.ticks for r in results) > 0
    if recording.experiment["settings"]["mode"] == "lockstep":
        for result in results:
            assert result.first_divergent_tick is None, result.as_json()
            assert result.max_abs_u == 0.0
            assert result.max_abs_x_hat == 0.0
        return
    first_irregular = first_irregular_ticks(path, recording)
    exact_ticks = 0
    for result in results:
        irregular = first_irregular[result.agent]
        pinned = sorted(
            k for k in recording.traces[result.agent].u if irregular is None or k < irregular
        )
        assert result.k[: len(pinned)] == pinned, (result.agent, irregular, result.k)
        exact_ticks += len(pinned)
        if irregular is None:
            assert result.first_divergent_tick is None, result.as_json()
            assert result.max_abs_u == 0.0
            assert result.max_abs_x_hat == 0.0
        else:
            divergent = result.first_divergent_tick
            assert divergent is None or divergent >= irregular, (result.as_json(), irregular)
    assert exact_ticks > 0, first_irregular


def test_a_parameter_change_diverges_and_json_is_one_object_per_agent(
    lead_follow: Path, tmp_path: Path
) -> None:
    result = hilswarm(
        "replay", str(lead_follow), "--set", "leader.max_wheel_speed_m_s=0.1", "--json",
        "--out", str(tmp_path / "plots"),
    )  # fmt: skip
    assert result.returncode == 0, result.stderr
    objects = [json.loads(line) for line in result.stdout.splitlines()]
    assert [o["agent"] for o in objects] == ["leader", "f1", "f2"]
    for o in objects:
        assert set(o) == {"agent", "ticks", "first_divergent_tick", "max_abs_u", "max_abs_x_hat"}
    leader, f1, _ = objects
    assert leader["first_divergent_tick"] == 1
    assert leader["max_abs_u"] > 0.05
    assert f1["first_divergent_tick"] is None  # it saw the recorded leader, unchanged
    assert (tmp_path / "plots" / "replay_leader.png").is_file()


def test_a_changed_controller_is_replayed_and_bad_names_exit_2(lead_follow: Path) -> None:
    changed = hilswarm(
        "replay", str(lead_follow), "--controller", "f1=follower", "--set", "f1.distance_m=0.5",
        "--agent", "f1", "--no-plot",
    )  # fmt: skip
    assert changed.returncode == 0, changed.stderr
    assert changed.stdout.startswith("f1: ") and "first divergent tick 1" in changed.stdout
    for bad in (
        ["--set", "leadr.kp=1"],
        ["--controller", "f1=no_such_controller"],
        ["--set", "leader.no_such_param=1"],
        ["--set", "kp=1"],
    ):
        result = hilswarm("replay", str(lead_follow), "--no-plot", *bad)
        assert result.returncode == 2, (bad, result.stdout, result.stderr)
        assert "Traceback" not in result.stderr
    assert "leader, f1, f2" in hilswarm("replay", str(lead_follow), "--set", "x.kp=1").stderr


def test_another_controller_gets_only_the_recorded_parameters_it_takes(tmp_path: Path) -> None:
    """The recorded ``consensus`` parameters (``gain``) are not ``static_gain``'s: replaying a0
    with ``static_gain`` leaves them out (it used to refuse the replay, "unknown parameter(s)
    ['gain']", whatever ``--set`` said) and takes ``--set a0.K``; a zero gain commands zero
    inputs, which diverge from the consensus run at its first controller step."""
    recording = record("consensus_ring.toml", tmp_path / "ring.mcap", 0.5)
    result = hilswarm(
        "replay", str(recording), "--controller", "a0=static_gain",
        "--set", "a0.K=[[0.0, 0.0], [0.0, 0.0]]", "--agent", "a0", "--json", "--no-plot",
    )  # fmt: skip
    assert result.returncode == 0, result.stderr
    (a0,) = [json.loads(line) for line in result.stdout.splitlines()]
    assert a0["agent"] == "a0" and a0["first_divergent_tick"] == 1, a0
    # the recorded controller keeps every recorded parameter: an unchanged replay is exact
    same = hilswarm(
        "replay", str(recording), "--controller", "a0=consensus", "--agent", "a0", "--json",
        "--no-plot",
    )  # fmt: skip
    assert same.returncode == 0, same.stderr
    assert json.loads(same.stdout)["first_divergent_tick"] is None
