"""What a run recording says about its signals and its run, beside the samples themselves.

* :func:`describe_agent` — the entry names and units of an agent's ``y``, ``u`` and ``x_hat``
  (from its vehicle's ``output_names``/``output_units``/``input_names``/``input_units`` and its
  controller's ``state_names``/``state_units``), and the calibration its vehicle runs with;
  built as ``hilswarm check`` builds them, without a board.
* :func:`run_metadata` — the one MCAP metadata record of a run (:data:`RUN_METADATA`): the
  experiment file's text, the git revision of the code when it is a checkout, the versions of
  the packages that shape the numbers, every calibration and the seed.

The recorder calls both before the first tick; nothing here runs per message.
"""

from __future__ import annotations

import json
import logging
import subprocess
from dataclasses import dataclass, field
from importlib import metadata as importlib_metadata
from pathlib import Path
from typing import Any

from hilswarm.agents.errors import HilswarmError
from hilswarm.orchestrator import calibration_report
from hilswarm.orchestrator.experiment import AgentSpec, Experiment

logger = logging.getLogger(__name__)

#: Name of the run's MCAP metadata record.
RUN_METADATA = "hilswarm.run"
#: Packages whose versions are recorded (those that shape a run's numbers or its file).
RECORDED_PACKAGES = (
    "hilswarm",
    "numpy",
    "scipy",
    "eclipse-zenoh",
    "mcap",
    "foxglove-sdk",
    "pyserial",
    "python-statemachine",
)
#: Bound on asking git for the revision [s].
GIT_TIMEOUT_S = 5.0


@dataclass(frozen=True)
class Signal:
    """Names and units of the entries of one vector signal (``""``: no unit)."""

    names: tuple[str, ...]
    units: dict[str, str] = field(default_factory=dict)


@dataclass
class AgentDescription:
    """What the recording states about one agent's signals (``None``: not known here)."""

    y: Signal | None = None
    u: Signal | None = None
    x_hat: Signal | None = None
    calibration: Any = None


def describe_agent(experiment: Experiment, spec: AgentSpec) -> AgentDescription:
    """Names and units of ``spec``'s signals and its calibration (what can be built here).

    A vehicle or controller that cannot be built here (a remote agent's class not installed)
    leaves its signals unnamed; the agent's calibration file is still read when it has one.
    """
    description = AgentDescription()
    vehicle = _build_vehicle(experiment, spec)
    if vehicle is not None:
        description.y = _signal(vehicle, "output_names", "output_units", "n_outputs")
        description.u = _signal(vehicle, "input_names", "input_units", "n_inputs")
        description.calibration = getattr(vehicle, "calibration", None)
    elif spec.calibration is not None:
        description.calibration = _load_calibration(spec)
    description.x_hat = _controller_signal(experiment, spec)
    return description


def _signal(owner: Any, names_attr: str, units_attr: str, size_attr: str) -> Signal | None:
    names = tuple(getattr(owner, names_attr, ()) or ())
    size = getattr(owner, size_attr, None)
    if not names or not isinstance(size, int) or len(names) != size:
        return None
    units = {str(k): str(v) for k, v in dict(getattr(owner, units_attr, {}) or {}).items()}
    return Signal(names, {name: units[name] for name in names if units.get(name)})


def _controller_signal(experiment: Experiment, spec: AgentSpec) -> Signal | None:
    """Names of ``x_hat`` from the controller's ``state_names`` (sized by its initial state)."""
    from hilswarm.agents.registry import resolve_controller  # noqa: PLC0415 - recording only

    _search_beside(experiment)
    try:
        controller = resolve_controller(spec.controller)()
        params = controller.validate_params(dict(spec.params))
        size = len(controller.initial_state(params))
        names = controller.state_names_for(size)
        units = dict(getattr(controller, "state_units", {}) or {})
    except (HilswarmError, ValueError, TypeError, ImportError, AttributeError) as exc:
        logger.warning("agent %s: x_hat entries not named: %s", spec.name, exc)
        return None
    if not names:
        return None
    return Signal(tuple(names), {n: str(units[n]) for n in names if units.get(n)})


def _search_beside(experiment: Experiment) -> None:
    from hilswarm.agents.registry import add_search_path  # noqa: PLC0415 - recording only

    add_search_path(experiment.path.parent)  # user "module:Class" names beside the file


def _build_vehicle(experiment: Experiment, spec: AgentSpec) -> Any:
    """The agent's vehicle built without a board (``None`` when that is not possible here)."""
    from hilswarm.agents.registry import resolve_vehicle  # noqa: PLC0415 - recording only

    _search_beside(experiment)
    kwargs: dict[str, Any] = {"name": spec.name, "dt": experiment.dt}
    if spec.pinout:
        kwargs["pinout"] = spec.pinout
    if spec.vehicle_params:
        kwargs["params"] = spec.vehicle_params
    if spec.initial_state:
        kwargs["initial_state"] = spec.initial_state
    if spec.calibration is not None:
        kwargs["calibration"] = spec.calibration
    try:
        return resolve_vehicle(spec.vehicle)(**kwargs)
    except (HilswarmError, ValueError, TypeError, OSError, ImportError) as exc:
        logger.warning("agent %s: vehicle not built for the recording: %s", spec.name, exc)
        return None


def _load_calibration(spec: AgentSpec) -> Any:
    from hilswarm.agents.calibration import Calibration  # noqa: PLC0415 - recording only

    try:
        return Calibration.from_file(spec.calibration)
    except (HilswarmError, ValueError, OSError) as exc:
        logger.warning("agent %s: calibration not recorded: %s", spec.name, exc)
        return None


def run_metadata(
    experiment: Experiment, calibrations: dict[str, Any] | None = None
) -> dict[str, str]:
    """The run's metadata record (string keys and values, as MCAP metadata must be).

    Keys: ``experiment_file`` (path), ``experiment_text`` (the file as loaded),
    ``git_revision`` (``""`` when the code is not a git checkout), ``packages`` (JSON name ->
    version), ``calibrations`` (JSON agent -> calibration as recorded on
    ``/<agent>/calibration``), ``seed`` (``""``: none).

    Args:
        experiment: the experiment as run.
        calibrations: agent -> its vehicle's calibration object (``None`` entries skipped).
    """
    recorded = {
        agent: calibration_report.calibration_as_json(calibration)
        for agent, calibration in (calibrations or {}).items()
        if calibration is not None
    }
    return {
        "experiment_file": str(experiment.path),
        "experiment_text": experiment.source_text or "",
        "git_revision": git_revision(Path(__file__).resolve().parent),
        "packages": json.dumps(package_versions(), sort_keys=True),
        "calibrations": json.dumps(recorded, sort_keys=True, default=str),
        "seed": "" if experiment.seed is None else str(experiment.seed),
    }


def package_versions(names: tuple[str, ...] = RECORDED_PACKAGES) -> dict[str, str]:
    """Installed versions of ``names`` (``""`` for one not installed)."""
    versions: dict[str, str] = {}
    for name in names:
        try:
            versions[name] = importlib_metadata.version(name)
        except importlib_metadata.PackageNotFoundError:
            versions[name] = ""
    return versions


def git_revision(folder: Path) -> str:
    """The git revision of the checkout holding ``folder`` (``+dirty`` when changed), or ``""``."""
    try:
        head = subprocess.run(
            ["git", "-C", str(folder), "rev-parse", "HEAD"],
            capture_output=True, text=True, timeout=GIT_TIMEOUT_S, check=False,
        )  # fmt: skip
        if head.returncode != 0:
            return ""
        status = subprocess.run(
            ["git", "-C", str(folder), "status", "--porcelain", "--untracked-files=no"],
            capture_output=True, text=True, timeout=GIT_TIMEOUT_S, check=False,
        )  # fmt: skip
    except (OSError, subprocess.SubprocessError):
        return ""
    revision = head.stdout.strip()
    return f"{revision}+dirty" if status.stdout.strip() else revision
