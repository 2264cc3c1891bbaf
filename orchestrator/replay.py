"""Replay a run recording through its controllers, recorded or changed (``hilswarm replay``).

For every agent with a recorded ``u``, the agent's controller (the one the experiment named,
or one given instead) runs again on what the agent saw during the run: at each tick ``k``
with a recorded ``u_k``, the ``u`` it had applied before (the previous recorded ``u``, zeros
at first), its own ``y_{k-1}`` and its neighbours' ``y_{k-1}`` (``None`` for a neighbour with
no ``y_{k-1}`` in the file), at the time the agent used (``t`` of the recorded ``u_k``). The
replayed ``u_k`` and ``x_hat_k`` are compared with the recorded ones.

Replaying a lockstep run unchanged is bit-exact: the agent computed exactly this, and the
recording keeps every float exactly (shortest round-trip text). A realtime run is bit-exact
only up to an agent's first tick ``k`` whose inputs the file does not pin down: the agent
skipped tick ``k-1`` (it then used older outputs; its replay stops there, having no
``y_{k-1}``), or a neighbour was late for tick ``k-1`` or lost (the agent used ``None`` for
it unless the late output reached it in time; docs/recording.md, Replay). Parameter changes
made during the run (``hilswarm set``) are not replayed.
"""

from __future__ import annotations

import logging
import math
import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from hilswarm.agents.control import ControlModel
from hilswarm.agents.errors import HilswarmError, RecordingError
from hilswarm.agents.mcap_io import iter_messages
from hilswarm.agents.record_schema import entry_names_units
from hilswarm.orchestrator.recover import check_mcap_magic

logger = logging.getLogger(__name__)


class ReplayError(RecordingError):
    """A replay cannot be set up (unknown agent, controller or parameter; no recording)."""


@dataclass
class AgentTrace:
    """What one agent did in a run, by tick: ``y_k``, ``u_k`` (with its time) and ``x_hat_k``."""

    y: dict[int, np.ndarray] = field(default_factory=dict)
    u: dict[int, tuple[float, np.ndarray]] = field(default_factory=dict)
    x_hat: dict[int, np.ndarray] = field(default_factory=dict)


@dataclass
class Recording:
    """The replayable content of a run recording."""

    experiment: dict[str, Any]
    traces: dict[str, AgentTrace]
    #: agent -> axis labels of the entries of its ``u`` (``"v_left [m/s]"``).
    input_labels: dict[str, tuple[str, ...]] = field(default_factory=dict)

    @property
    def agent_names(self) -> tuple[str, ...]:
        """Agents in graph order."""
        return tuple(self.experiment.get("graph", {}).get("agents", ()))

    def neighbours(self, name: str) -> tuple[str, ...]:
        """Agents whose output ``name`` receives, in graph order (as the agent had them)."""
        names = self.agent_names
        row = self.experiment["graph"]["adjacency"][names.index(name)]
        return tuple(other for other, edge in zip(names, row, strict=True) if edge)

    @property
    def dt(self) -> float:
        """Control period [s]."""
        return 1.0 / float(self.experiment["settings"]["rate_hz"])


@dataclass
class AgentReplay:
    """The outcome for one agent (the ``--json`` object, see :meth:`as_json`).

    Attributes:
        agent: agent name.
        ticks: ticks replayed.
        first_divergent_tick: first tick whose replayed ``u`` or ``x_hat`` differs from the
            recorded one at all (``None``: bit-exact).
        max_abs_u: largest absolute difference of an entry of ``u``.
        max_abs_x_hat: the same for ``x_hat`` (``None`` when the sizes differ, e.g. a changed
            controller with another state).
        input_names: names (and units) of the entries of ``u``, for the plot.
        k, t, u_recorded, u_replayed: ticks, times [s] and the two ``u`` series.
    """

    agent: str
    ticks: int = 0
    first_divergent_tick: int | None = None
    max_abs_u: float = 0.0
    max_abs_x_hat: float | None = 0.0
    input_names: tuple[str, ...] = ()
    k: list[int] = field(default_factory=list)
    t: list[float] = field(default_factory=list)
    u_recorded: list[np.ndarray] = field(default_factory=list)
    u_replayed: list[np.ndarray] = field(default_factory=list)

    def as_json(self) -> dict[str, Any]:
        """``{"agent", "ticks", "first_divergent_tick", "max_abs_u", "max_abs_x_hat"}``."""
        return {
            "agent": self.agent,
            "ticks": self.ticks,
            "first_divergent_tick": self.first_divergent_tick,
            "max_abs_u": self.max_abs_u,
            "max_abs_x_hat": self.max_abs_x_hat,
        }


def load_recording(path: str | os.PathLike[str]) -> Recording:
    """Read ``/experiment`` and every agent's ``y``, ``u`` and ``x_hat`` (values exactly).

    Raises:
        RecordingError: no such file, a directory, a file that is not MCAP.
        ReplayError: no ``/experiment`` message in it.
    """
    path = Path(path)
    check_mcap_magic(path)
    experiment: dict[str, Any] | None = None
    traces: dict[str, AgentTrace] = {}
    schemas: dict[str, dict[str, Any]] = {}
    for topic, _, message in iter_messages(path, schemas=schemas):
        if topic == "/experiment":
            experiment = message
            continue
        parts = topic[1:].split("/")
        if len(parts) != 2 or parts[1] not in ("y", "u", "x_hat"):
            continue
        trace = traces.setdefault(parts[0], AgentTrace())
        k = int(message["k"])
        values = np.array([math.nan if v is None else v for v in message["values"]], float)
        if parts[1] == "y":
            trace.y[k] = values
        elif parts[1] == "u":
            trace.u[k] = (float(message["t"]), values)
        else:
            trace.x_hat[k] = values
    if experiment is None:
        raise ReplayError(f"{path} has no /experiment message: not a run recording")
    labels = {}
    for topic, schema in schemas.items():
        if topic.endswith("/u"):
            names, units = entry_names_units(schema)
            labels[topic[1:-2]] = tuple(
                f"{n} [{unit}]" if unit else n for n, unit in zip(names, units, strict=True)
            )
    return Recording(experiment, traces, labels)


def replay(
    recording: Recording,
    *,
    controllers: Mapping[str, str] | None = None,
    params: Mapping[str, Mapping[str, Any]] | None = None,
    agents: Sequence[str] | None = None,
    search_path: str | os.PathLike[str] | None = None,
) -> list[AgentReplay]:
    """Replay every agent with a recorded ``u`` (or only ``agents``); see the module docstring.

    Args:
        recording: from :func:`load_recording`.
        controllers: agent -> controller (registry name or ``"module:Class"``) used instead of
            the recorded one.
        params: agent -> parameter changes merged over the recorded parameters (for an agent
            replayed with another controller, over those of them that controller takes).
        agents: only these agents (default: every agent with a recorded ``u``).
        search_path: folder searched for user ``module:Class`` names (the experiment's).

    Raises:
        ReplayError: an unknown agent, a controller that cannot be built, parameters it
            rejects.
    """
    from hilswarm.agents.registry import (  # noqa: PLC0415 - user code only when replaying
        add_search_path,
        resolve_controller,
    )

    if search_path is not None:
        add_search_path(search_path)
    names = recording.agent_names
    controllers = dict(controllers or {})
    params = dict(params or {})
    for what, mapping in (("--controller", controllers), ("--set", params), ("agent", agents)):
        unknown = sorted(set(mapping or ()) - set(names))
        if unknown:
            raise ReplayError(f"{what}: unknown agent(s) {unknown}; agents: {', '.join(names)}")
    specs = recording.experiment.get("agents", {})
    results = []
    for name in agents or names:
        trace = recording.traces.get(name)
        if trace is None or not trace.u:
            logger.info("%s: no recorded u (no controller steps): not replayed", name)
            continue
        spec = specs.get(name, {})
        controller_name = controllers.get(name, spec.get("controller"))
        try:
            controller = resolve_controller(str(controller_name))()
            recorded = _recorded_params(name, spec, controller, controller_name)
            model = ControlModel(
                controller,
                dt=recording.dt,
                n_inputs=len(next(iter(trace.u.values()))[1]),
                params={**recorded, **params.get(name, {})},
            )
        except (HilswarmError, ImportError, ValueError, TypeError) as exc:
            raise ReplayError(f"agent {name}: controller {controller_name!r}: {exc}") from exc
        results.append(_replay_agent(recording, name, trace, model))
    return results


def _recorded_params(
    name: str, spec: Mapping[str, Any], controller: Any, controller_name: object
) -> dict[str, Any]:
    """The recorded parameters the replayed controller takes: all of them for the recorded
    controller; for another one (``--controller``) those it also has (``default_params``), the
    others left out (logged): they were the recorded controller's."""
    recorded = dict(spec.get("params") or {})
    if str(controller_name) == str(spec.get("controller")):
        return recorded
    known = getattr(controller, "default_params", {}) or {}
    left_out = sorted(set(recorded) - set(known))
    if left_out:
        logger.info(
            "%s: recorded parameters %s are not %s's: left out of the replay",
            name,
            ", ".join(left_out),
            controller_name,
        )
    return {key: value for key, value in recorded.items() if key in known}


def _replay_agent(
    recording: Recording, name: str, trace: AgentTrace, model: ControlModel
) -> AgentReplay:
    result = AgentReplay(name, input_names=recording.input_labels.get(name, ()))
    neighbours = recording.neighbours(name)
    others = {n: recording.traces.get(n, AgentTrace()) for n in neighbours}
    u_applied = np.zeros(model.n_inputs)
    for k in sorted(trace.u):
        t_u, u_recorded = trace.u[k]
        y_prev = trace.y.get(k - 1)
        if y_prev is None:
            logger.warning("%s: no y_%d recorded: replay stops at tick %d", name, k - 1, k)
            break
        seen = {n: others[n].y.get(k - 1) for n in neighbours}
        try:
            u = model.step(u_applied, y_prev, t=t_u, neighbours=seen)
        except HilswarmError as exc:
            logger.warning("%s: the controller failed at tick %d: %s", name, k, exc)
            break
        result.ticks += 1
        diverged = not _same(u, u_recorded)
        result.max_abs_u = max(result.max_abs_u, _max_abs(u, u_recorded))
        x_recorded = trace.x_hat.get(k)
        x_hat = model.x_hat
        if x_recorded is not None or x_hat.size:
            x_recorded = np.zeros(0) if x_recorded is None else x_recorded
            diverged = diverged or not _same(x_hat, x_recorded)
            if result.max_abs_x_hat is not None:
                result.max_abs_x_hat = (
                    None
                    if x_hat.shape != x_recorded.shape
                    else max(result.max_abs_x_hat, _max_abs(x_hat, x_recorded))
                )
        if diverged and result.first_divergent_tick is None:
            result.first_divergent_tick = k
        result.k.append(k)
        result.t.append(t_u)
        result.u_recorded.append(u_recorded)
        result.u_replayed.append(u)
        u_applied = u_recorded  # what the vehicle really applied
    return result


def _same(a: np.ndarray, b: np.ndarray) -> bool:
    """Bit-exact equality (NaN equals NaN)."""
    return a.shape == b.shape and bool(np.array_equal(a, b, equal_nan=True))


def _max_abs(a: np.ndarray, b: np.ndarray) -> float:
    if a.shape != b.shape:
        return math.inf
    if not a.size:
        return 0.0
    difference = np.abs(a - b)
    both_nan = np.isnan(a) & np.isnan(b)
    difference[both_nan] = 0.0
    return float(np.nanmax(np.where(np.isnan(difference), np.inf, difference)))


def plot_replay(results: Sequence[AgentReplay], out_dir: str | os.PathLike[str]) -> list[Path]:
    """One PNG per agent: recorded and replayed ``u`` against experiment time.

    ``out_dir`` is created when the first PNG is written (none: no folder).
    """
    import matplotlib as mpl  # noqa: PLC0415 - only for the plots

    mpl.use("Agg")
    import matplotlib.pyplot as plt  # noqa: PLC0415

    out = Path(out_dir)
    written = []
    for result in results:
        if not result.t:
            continue
        recorded, replayed = np.array(result.u_recorded), np.array(result.u_replayed)
        width = recorded.shape[1] if recorded.ndim == 2 else 0
        if width == 0 or replayed.shape != recorded.shape:
            continue
        figure, axes = plt.subplots(width, 1, sharex=True, figsize=(8, 2 + 1.6 * width))
        axes = np.atleast_1d(axes)
        for i, axis in enumerate(axes):
            axis.plot(result.t, recorded[:, i], label="recorded", linewidth=1.6)
            axis.plot(result.t, replayed[:, i], "--", label="replayed", linewidth=1.2)
            axis.set_ylabel(result.input_names[i] if i < len(result.input_names) else f"u[{i}]")
            axis.grid(True, alpha=0.3)
        if result.first_divergent_tick is not None:
            when = result.t[result.k.index(result.first_divergent_tick)]
            for axis in axes:
                axis.axvline(when, color="red", linestyle=":", label="first divergence")
        axes[-1].set_xlabel("experiment time t [s]")
        axes[0].legend(loc="best", fontsize="small")
        verdict = (
            "bit-exact"
            if result.first_divergent_tick is None
            else f"diverges at tick {result.first_divergent_tick}, max |Δu| {result.max_abs_u:.3g}"
        )
        figure.suptitle(f"replay of {result.agent}: {verdict}")
        figure.tight_layout()
        target = out / f"replay_{result.agent}.png"
        out.mkdir(parents=True, exist_ok=True)
        figure.savefig(target, dpi=110)
        plt.close(figure)
        written.append(target)
    return written
