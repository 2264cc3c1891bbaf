"""The Controller contract and the ControlModel that runs a controller once per tick.

This replaces the thesis' Simulink observer/controller model and its ``ControlModel`` (thesis
2.1.3, A.3). A controller sees, at tick ``k``:

* ``u_k`` — the input the vehicle actually applied (after its limits), and
* ``y_k`` — the output the vehicle sensed,

and returns ``u_{k+1}`` (the input to apply next) together with its internal state
``x_hat_{k+1}`` (e.g. an observer's estimate). The :class:`ControlModel` keeps ``x_hat`` between
ticks (starting from an initial condition, zeros by default), the tick counter ``k``, the period
``dt`` [s] and the parameters, which may be replaced at any time (waypoints, gains); the
controller validates every new parameter set. It records ``u_{k+1}`` and ``x_hat_{k+1}`` in
telemetry channels.

Controllers are built without arguments and get everything from plain, TOML-like parameters
(lists become numpy arrays in :meth:`Controller.validate_params`), so experiment files can name
them: ``static_gain``, ``state_feedback``, ``discrete_state_space`` (see ``registry.py``).
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Any, ClassVar

import numpy as np
from hilswarm.agents.errors import ControllerError
from hilswarm.agents.sim.plant import METHODS as INTEGRATORS
from hilswarm.agents.sim.plant import integrate
from hilswarm.agents.telemetry import Channel, Telemetry
from numpy.typing import ArrayLike

_FLOAT64 = np.dtype(np.float64)
#: The neighbours of a tick without any.
_NO_NEIGHBOURS: Mapping[str, np.ndarray | None] = MappingProxyType({})


def _frozen(values: ArrayLike) -> np.ndarray:
    """A read-only float array of ``values``: a copy, unless ``values`` already is a read-only
    float array owning its data (nobody can change it behind the controller's back)."""
    if (
        type(values) is np.ndarray
        and values.dtype == _FLOAT64
        and not values.flags.writeable
        and values.flags.owndata
    ):
        return values
    array = np.array(values, dtype=np.float64)
    array.flags.writeable = False
    return array


def all_finite(values: np.ndarray) -> bool:
    """True when every entry of the float array ``values`` is finite (no NaN, no ±inf).

    Plain float checks for the few entries a controller's vectors have (several times cheaper
    than ``np.all(np.isfinite(values))`` there), numpy for larger arrays.
    """
    if values.size <= _SMALL:
        return all(map(math.isfinite, values.ravel().tolist()))
    return bool(np.isfinite(values).all())


#: Up to this many entries plain float arithmetic beats a numpy call.
_SMALL = 16


def _is_vector(value: object, size: int) -> bool:
    """True for a float64 numpy vector of ``size`` entries (needs no conversion)."""
    return type(value) is np.ndarray and value.dtype == _FLOAT64 and value.shape == (size,)


@dataclass(frozen=True)
class TickInput:
    """What a controller sees at tick ``k``.

    Attributes:
        k: tick index (0 at the first tick).
        t: experiment time of the tick [s].
        dt: control period [s].
        u: ``u_k``, the input the vehicle applied (read-only array).
        y: ``y_k``, the output the vehicle sensed (read-only array).
        neighbours: neighbours' ``y_k`` by agent name; ``None`` means no data this tick.
        neighbour_poses: for a controller with ``uses_neighbour_poses``: each neighbour's
            newest mocap pose ``[x, y, z (m), roll, pitch, yaw (rad)]`` (world frame) by agent
            name, ``None`` while its tracking is lost; empty otherwise.
    """

    k: int
    t: float
    dt: float
    u: np.ndarray
    y: np.ndarray
    neighbours: Mapping[str, np.ndarray | None] = field(
        default_factory=lambda: MappingProxyType({})
    )
    neighbour_poses: Mapping[str, np.ndarray | None] = field(
        default_factory=lambda: MappingProxyType({})
    )


def _tick_input(
    k: int,
    t: float,
    dt: float,
    *,
    u: np.ndarray,
    y: np.ndarray,
    neighbours: Mapping[str, np.ndarray | None],
) -> TickInput:
    """``TickInput(k, t, dt, u, y, neighbours)`` for values the ControlModel has checked.

    Fills the instance dictionary directly instead of going through the frozen dataclass'
    ``__init__`` (one ``object.__setattr__`` per field): the same object, at a third of the
    cost, which matters once per tick. The result is as frozen as any other TickInput.
    """
    tick = _new_object(TickInput)
    fields = tick.__dict__
    fields["k"] = k
    fields["t"] = t
    fields["dt"] = dt
    fields["u"] = u
    fields["y"] = y
    fields["neighbours"] = neighbours
    fields["neighbour_poses"] = _NO_NEIGHBOURS
    return tick


_new_object = object.__new__


class Controller(ABC):
    """A discrete-time controller/observer: ``(u_k, y_k, x_hat_k) -> (u_{k+1}, x_hat_{k+1})``.

    Subclasses set :attr:`default_params` (every parameter name they accept, with its default),
    may override :meth:`validate_params` (call ``super()`` first, then convert and check values)
    and :meth:`initial_state`, and implement :meth:`step`. A controller keeps no per-run state
    itself: the :class:`ControlModel` owns ``x_hat``, ``k`` and the parameters.
    """

    #: Size of ``x_hat`` when it does not depend on the parameters.
    n_states: ClassVar[int] = 0
    #: Every accepted parameter and its default (``None``: required or computed).
    default_params: ClassVar[Mapping[str, Any]] = {}
    #: Names of the entries of ``x_hat`` (recorded as the fields of ``/<agent>/x_hat``);
    #: empty, or not one per entry: ``x0``, ``x1``, ... (see :meth:`state_names_for`).
    state_names: ClassVar[tuple[str, ...]] = ()
    #: Unit of each named state entry (``{"integral_m_s": "m s"}``); absent: no unit.
    state_units: ClassVar[Mapping[str, str]] = {}
    #: With a ``[mocap]`` system: the agent also receives its graph neighbours' mocap poses
    #: (``TickInput.neighbour_poses``), not only their outputs.
    uses_neighbour_poses: ClassVar[bool] = False

    @property
    def name(self) -> str:
        """Name used in error messages (the class name)."""
        return type(self).__name__

    def validate_params(self, params: Mapping[str, Any]) -> dict[str, Any]:
        """Merge ``params`` over :attr:`default_params` and reject unknown names.

        Must accept its own output again (validation is idempotent).

        Raises:
            ControllerError: an unknown parameter name.
        """
        if not isinstance(params, Mapping):
            raise ControllerError(
                f"{self.name}: parameters must be a mapping, got {type(params).__name__}"
            )
        unknown = sorted(set(params) - set(self.default_params))
        if unknown:
            raise ControllerError(
                f"{self.name}: unknown parameter(s) {unknown}; "
                f"accepted: {sorted(self.default_params)}"
            )
        return {**self.default_params, **params}

    def initial_state(self, params: Mapping[str, Any]) -> np.ndarray:
        """``x_hat_0`` when the ControlModel is given none: zeros of :attr:`n_states`."""
        return np.zeros(self.n_states)

    def state_names_for(self, size: int) -> tuple[str, ...]:
        """Names of the ``size`` entries of ``x_hat``: :attr:`state_names`, else ``x0``..."""
        names = tuple(self.state_names)
        return names if len(names) == size else tuple(f"x{i}" for i in range(size))

    def params_changed(
        self, old: Mapping[str, Any], new: Mapping[str, Any], x_hat: np.ndarray
    ) -> np.ndarray:
        """``x_hat`` to continue with after the parameters changed at run time (``set``).

        Called by :meth:`ControlModel.replace_params` with the validated parameters before and
        after the change; the default keeps the state. A controller whose state must restart
        on some change (a new waypoint list) returns the restarted state here, so no marker of
        the parameters has to live in ``x_hat``.
        """
        del old, new
        return x_hat

    @abstractmethod
    def step(
        self, tick: TickInput, x_hat: np.ndarray, params: Mapping[str, Any]
    ) -> tuple[np.ndarray, np.ndarray]:
        """Compute ``(u_{k+1}, x_hat_{k+1})`` from the tick and ``x_hat_k``."""


# --- parameter helpers --------------------------------------------------------------------


def param_matrix(controller: Controller, name: str, value: Any) -> np.ndarray:
    """A finite 2-D float matrix from a TOML-like value (a flat list is one row, a scalar 1x1).

    Raises:
        ControllerError: missing, not numeric, more than 2-D, ragged or non-finite.
    """
    if value is None:
        raise ControllerError(f"{controller.name}: parameter {name!r} is required")
    try:
        matrix = np.array(value, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise ControllerError(
            f"{controller.name}: parameter {name!r} must be a numeric matrix (list of rows): {exc}"
        ) from None
    if matrix.ndim == 0:
        matrix = matrix.reshape(1, 1)
    elif matrix.ndim == 1:
        matrix = matrix.reshape(1, -1)
    if matrix.ndim != 2:
        raise ControllerError(
            f"{controller.name}: parameter {name!r} must be 2-D, got shape {matrix.shape}"
        )
    if not np.all(np.isfinite(matrix)):
        raise ControllerError(f"{controller.name}: parameter {name!r} has non-finite entries")
    return matrix


def param_vector(
    controller: Controller, name: str, value: Any, size: int | None = None
) -> np.ndarray:
    """A finite 1-D float vector from a TOML-like value (a scalar is one entry).

    Raises:
        ControllerError: not numeric, wrong size or non-finite.
    """
    try:
        vector = np.array(value, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError) as exc:
        raise ControllerError(
            f"{controller.name}: parameter {name!r} must be a list of numbers: {exc}"
        ) from None
    if size is not None and vector.shape != (size,):
        raise ControllerError(
            f"{controller.name}: parameter {name!r} must have {size} entries, "
            f"got shape {vector.shape}"
        )
    if not np.all(np.isfinite(vector)):
        raise ControllerError(f"{controller.name}: parameter {name!r} has non-finite entries")
    return vector


def _check_vector(controller: Controller, what: str, value: ArrayLike, size: int) -> np.ndarray:
    try:
        vector = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise ControllerError(f"{controller.name}: {what} is not numeric: {exc}") from None
    if vector.shape != (size,):
        raise ControllerError(
            f"{controller.name}: {what} must have shape ({size},), got {vector.shape}"
        )
    return vector


# --- the ControlModel ---------------------------------------------------------------------


class ControlModel:
    """Runs a :class:`Controller` exactly once per tick and keeps its state between ticks.

    Args:
        controller: the controller to run.
        dt: control period [s] (> 0).
        n_inputs: size of ``u`` (the vehicle's number of inputs).
        n_outputs: size of ``y``; ``None`` skips that check.
        params: controller parameters (validated by the controller).
        x0: initial ``x_hat`` (default: :meth:`Controller.initial_state`).
        t0: experiment time of tick 0 [s] (used when :meth:`step` gets no ``t``).
        input_names: names of the inputs for the ``u`` telemetry channel (default u0, u1, ...).

    Telemetry (:attr:`history`): channel ``"u"`` holds ``u_{k+1}`` and channel ``"x_hat"``
    holds ``x_hat_{k+1}`` (present only when the state is non-empty), both stamped with the
    tick ``k`` and time ``t`` at which they were computed.

    Raises:
        ControllerError: bad ``dt``, sizes, parameters or initial state.
    """

    def __init__(
        self,
        controller: Controller,
        *,
        dt: float,
        n_inputs: int,
        n_outputs: int | None = None,
        params: Mapping[str, Any] | None = None,
        x0: ArrayLike | None = None,
        t0: float = 0.0,
        input_names: Sequence[str] | None = None,
    ) -> None:
        if not isinstance(controller, Controller):
            raise ControllerError(
                f"ControlModel needs a Controller instance, got {type(controller).__name__}"
            )
        self.controller = controller
        if isinstance(dt, bool) or not isinstance(dt, int | float) or not dt > 0:
            raise ControllerError(
                f"{controller.name}: dt must be a positive period [s], got {dt!r}"
            )
        if not math.isfinite(dt):
            raise ControllerError(f"{controller.name}: dt must be finite [s], got {dt!r}")
        for label, size in (("n_inputs", n_inputs), ("n_outputs", n_outputs)):
            if size is not None and (
                isinstance(size, bool) or not isinstance(size, int) or size < 0
            ):
                raise ControllerError(
                    f"{controller.name}: {label} must be an int >= 0, got {size!r}"
                )
        self.dt: float = float(dt)
        self.t0: float = float(t0)
        self.n_inputs: int = n_inputs
        self.n_outputs: int | None = n_outputs
        self._given_params: dict[str, Any] = dict(params or {})
        self._params: dict[str, Any] = controller.validate_params(self._given_params)
        self._params_view: Mapping[str, Any] = MappingProxyType(self._params)
        self._x0 = None if x0 is None else np.array(x0, dtype=np.float64).reshape(-1)
        self._k = 0
        self._x_hat = self._initial_x_hat()
        #: Gives the neighbours' mocap poses for ``TickInput.neighbour_poses`` (set by the
        #: agent when the controller ``uses_neighbour_poses``), or ``None``.
        self.neighbour_poses: Callable[[], Mapping[str, np.ndarray | None]] | None = None
        names = (
            tuple(input_names)
            if input_names is not None
            else tuple(f"u{i}" for i in range(n_inputs))
        )
        if len(names) != n_inputs:
            raise ControllerError(
                f"{controller.name}: {n_inputs} input names expected, got {names}"
            )
        self.history = Telemetry()
        self._u_channel: Channel | None = (
            self.history.add_channel("u", names) if n_inputs > 0 else None
        )
        self._x_channel: Channel | None = None
        self._ensure_x_channel()

    # -- state ---------------------------------------------------------------------------

    def _initial_x_hat(self) -> np.ndarray:
        if self._x0 is not None:
            return self._x0.copy()
        x_hat = self.controller.initial_state(self._params)
        return np.array(x_hat, dtype=np.float64).reshape(-1)

    def _ensure_x_channel(self) -> None:
        size = self._x_hat.shape[0]
        if size == 0 or self._x_channel is not None:
            return
        self._x_channel = self.history.add_channel("x_hat", self.controller.state_names_for(size))

    @property
    def k(self) -> int:
        """Index of the next tick to run (0 before the first :meth:`step`)."""
        return self._k

    @property
    def x_hat(self) -> np.ndarray:
        """Current controller state ``x_hat_k`` (a copy)."""
        return self._x_hat.copy()

    @property
    def params(self) -> Mapping[str, Any]:
        """The validated parameters (read-only view; replace them with :meth:`set_params`)."""
        return self._params_view

    def set_params(self, *, reset_state: bool = False, **changes: Any) -> None:
        """Change some parameters; the controller validates the whole new set first.

        The changes are merged into the parameters as given (not the validated ones), so
        values the controller derives from others (defaults sized by a matrix) are derived
        again. On a validation error nothing changes. ``reset_state=True`` also restarts
        ``x_hat`` from the initial condition (needed when the state size changes).

        Raises:
            ControllerError: the controller rejects the new parameters.
        """
        self.replace_params({**self._given_params, **changes}, reset_state=reset_state)

    def replace_params(self, params: Mapping[str, Any], *, reset_state: bool = False) -> None:
        """Replace all parameters (missing ones take the controller's defaults)."""
        given = dict(params)
        validated = self.controller.validate_params(given)
        old = self._params
        self._given_params, self._params = given, validated
        self._params_view = MappingProxyType(validated)
        if reset_state:
            self._x_hat = self._initial_x_hat()
            self._ensure_x_channel()
        else:
            x_hat = self.controller.params_changed(old, validated, self._x_hat.copy())
            self._x_hat = np.array(x_hat, dtype=np.float64).reshape(self._x_hat.shape)

    def reset(self, x0: ArrayLike | None = None) -> None:
        """Restart at tick 0 with ``x0`` (or the initial condition); history is cleared."""
        if x0 is not None:
            self._x0 = np.array(x0, dtype=np.float64).reshape(-1)
        self._k = 0
        self._x_hat = self._initial_x_hat()
        self.history.clear()
        self._ensure_x_channel()

    # -- one tick --------------------------------------------------------------------------

    def step(
        self,
        u_k: ArrayLike,
        y_k: ArrayLike,
        *,
        t: float | None = None,
        neighbours: Mapping[str, np.ndarray | None] | None = None,
    ) -> np.ndarray:
        """Run the controller for tick ``k`` and return ``u_{k+1}``.

        Args:
            u_k: input the vehicle applied at tick ``k`` (``n_inputs`` numbers).
            y_k: output the vehicle sensed at tick ``k``.
            t: experiment time of the tick [s] (default ``t0 + k * dt``).
            neighbours: neighbours' outputs ``y_k`` by name (``None`` entries: no data).

        Raises:
            ControllerError: wrong input/output size, or the controller returned a ``u`` or
                ``x_hat`` of the wrong shape, or a non-finite ``u``.
        """
        controller = self.controller
        n_inputs = self.n_inputs
        u = u_k if _is_vector(u_k, n_inputs) else _check_vector(controller, "u_k", u_k, n_inputs)
        if type(y_k) is np.ndarray and y_k.dtype == _FLOAT64 and y_k.ndim == 1:
            y = y_k
        else:
            y = np.asarray(y_k, dtype=np.float64).reshape(-1)
        if self.n_outputs is not None and y.shape != (self.n_outputs,):
            raise ControllerError(
                f"{controller.name}: y_k must have shape ({self.n_outputs},), got {y.shape}"
            )
        tick_time = self.t0 + self._k * self.dt if t is None else float(t)
        frozen_neighbours = (
            MappingProxyType(
                {
                    name: None if value is None else _frozen(value)
                    for name, value in neighbours.items()
                }
            )
            if neighbours
            else _NO_NEIGHBOURS
        )
        tick = _tick_input(
            self._k, tick_time, self.dt, u=_frozen(u), y=_frozen(y), neighbours=frozen_neighbours
        )
        if self.neighbour_poses is not None:
            tick.__dict__["neighbour_poses"] = MappingProxyType(dict(self.neighbour_poses()))
        n_states = self._x_hat.shape[0]
        result = controller.step(tick, self._x_hat.copy(), self._params_view)
        if not isinstance(result, tuple) or len(result) != 2:
            raise ControllerError(
                f"{controller.name}.step must return (u_next, x_hat_next), got {type(result)}"
            )
        u_next, x_next = result
        if not _is_vector(u_next, n_inputs):
            u_next = _check_vector(controller, "returned u_{k+1}", u_next, n_inputs)
        if not _is_vector(x_next, n_states):
            x_next = _check_vector(controller, "returned x_hat_{k+1}", x_next, n_states)
        if not all_finite(u_next):
            raise ControllerError(
                f"{controller.name}: returned a non-finite u_{{k+1}} at tick {self._k}: {u_next}"
            )
        self._x_hat = np.array(x_next, dtype=np.float64)
        u_next = np.array(u_next, dtype=np.float64)
        if self._u_channel is not None:
            self._u_channel.append(self._k, tick_time, u_next)
        if self._x_channel is not None:
            self._x_channel.append(self._k, tick_time, self._x_hat)
        self._k += 1
        return u_next


# --- helpers ------------------------------------------------------------------------------


class StaticGain(Controller):
    """``u_{k+1} = K y_k``. Parameters: ``K`` (n_inputs x n_outputs matrix)."""

    default_params: ClassVar[Mapping[str, Any]] = {"K": None}

    def validate_params(self, params: Mapping[str, Any]) -> dict[str, Any]:
        merged = super().validate_params(params)
        merged["K"] = param_matrix(self, "K", merged["K"])
        return merged

    def step(
        self, tick: TickInput, x_hat: np.ndarray, params: Mapping[str, Any]
    ) -> tuple[np.ndarray, np.ndarray]:
        gain = params["K"]
        y = _check_vector(self, "y_k", tick.y, gain.shape[1])
        return gain @ y, x_hat


class StateFeedback(Controller):
    """Full-state feedback ``u_{k+1} = u_ref - K (y_k - reference)``.

    Parameters:
        K: gain, n_inputs x n_outputs (the output is the state, e.g. thesis eq. 3.4).
        reference: the set-point of ``y`` (default zeros), same units as ``y``.
        u_ref: feed-forward input (default zeros), same units as ``u``.
    """

    default_params: ClassVar[Mapping[str, Any]] = {"K": None, "reference": None, "u_ref": None}

    def validate_params(self, params: Mapping[str, Any]) -> dict[str, Any]:
        merged = super().validate_params(params)
        gain = param_matrix(self, "K", merged["K"])
        n_inputs, n_outputs = gain.shape
        merged["K"] = gain
        merged["reference"] = (
            np.zeros(n_outputs)
            if merged["reference"] is None
            else param_vector(self, "reference", merged["reference"], n_outputs)
        )
        merged["u_ref"] = (
            np.zeros(n_inputs)
            if merged["u_ref"] is None
            else param_vector(self, "u_ref", merged["u_ref"], n_inputs)
        )
        return merged

    def step(
        self, tick: TickInput, x_hat: np.ndarray, params: Mapping[str, Any]
    ) -> tuple[np.ndarray, np.ndarray]:
        gain = params["K"]
        y = _check_vector(self, "y_k", tick.y, gain.shape[1])
        return params["u_ref"] - gain @ (y - params["reference"]), x_hat


class DiscreteStateSpace(Controller):
    """A linear discrete-time controller/observer driven by ``w_k = [u_k; y_k]``.

    Contract (one tick)::

        u_{k+1}     = C x_hat_k + D w_k
        x_hat_{k+1} = A x_hat_k + B w_k

    Parameters: ``A`` (n x n), ``B`` (n x (m + p)), ``C`` (m x n), ``D`` (m x (m + p)) where
    ``m`` = number of inputs (rows of ``C``) and ``p`` = number of outputs; ``x0`` optional
    initial state (default zeros). ``n = 0`` is allowed with ``A``/``B``/``C`` empty lists:
    then ``u_{k+1} = D w_k``.

    An observer-based law that uses the *updated* estimate, ``u_{k+1} = -K x_hat_{k+1}``, is
    this form with ``C = -K A`` and ``D = -K B``.
    """

    default_params: ClassVar[Mapping[str, Any]] = {
        "A": None,
        "B": None,
        "C": None,
        "D": None,
        "x0": None,
    }

    def validate_params(self, params: Mapping[str, Any]) -> dict[str, Any]:
        merged = super().validate_params(params)
        d = param_matrix(self, "D", merged["D"])
        m, width = d.shape
        p = width - m
        if p < 0:
            raise ControllerError(
                f"{self.name}: D must be m x (m + p) with m = its rows, got shape {d.shape}"
            )
        a = self._optional_matrix("A", merged["A"])
        n = 0 if a is None else a.shape[0]
        expected = {"A": (n, n), "B": (n, m + p), "C": (m, n)}
        matrices = {
            "A": a,
            "B": self._optional_matrix("B", merged["B"]),
            "C": self._optional_matrix("C", merged["C"]),
        }
        for key, shape in expected.items():
            matrix = matrices[key]
            if matrix is None:
                matrix = np.zeros(shape)
            if matrix.shape != shape:
                raise ControllerError(
                    f"{self.name}: {key} must have shape {shape} (n={n} states, m={m} inputs, "
                    f"p={p} outputs), got {matrix.shape}"
                )
            merged[key] = matrix
        merged["D"] = d
        merged["x0"] = (
            np.zeros(n) if merged["x0"] is None else param_vector(self, "x0", merged["x0"], n)
        )
        return merged

    def _optional_matrix(self, name: str, value: Any) -> np.ndarray | None:
        if value is None or (isinstance(value, list | tuple | np.ndarray) and len(value) == 0):
            return None
        return param_matrix(self, name, value)

    def initial_state(self, params: Mapping[str, Any]) -> np.ndarray:
        return np.array(params["x0"], dtype=np.float64)

    def step(
        self, tick: TickInput, x_hat: np.ndarray, params: Mapping[str, Any]
    ) -> tuple[np.ndarray, np.ndarray]:
        m = params["D"].shape[0]
        p = params["D"].shape[1] - m
        u = _check_vector(self, "u_k", tick.u, m)
        y = _check_vector(self, "y_k", tick.y, p)
        w = np.concatenate([u, y])
        u_next = params["C"] @ x_hat + params["D"] @ w
        x_next = params["A"] @ x_hat + params["B"] @ w
        return u_next, x_next


class ContinuousModel(Controller):
    """A continuous-time controller/observer advanced over one tick by a fixed-step method.

    Subclasses implement :meth:`derivative` (``dx_hat/dt``) and :meth:`output`. During the
    tick ``[t_k, t_k + dt]`` the inputs ``u_k`` and ``y_k`` are held constant (zero-order
    hold); the state is integrated with ``substeps`` steps of ``"euler"`` (the thesis' ode1)
    or ``"rk4"`` (its ode4), and ``u_{k+1} = output(t_k + dt, x_hat_{k+1}, u_k, y_k)``.

    Parameters (beside the subclass' own): ``integrator`` (``"euler"`` default or ``"rk4"``),
    ``substeps`` (int >= 1, default 1).
    """

    default_params: ClassVar[Mapping[str, Any]] = {"integrator": "euler", "substeps": 1}

    def validate_params(self, params: Mapping[str, Any]) -> dict[str, Any]:
        merged = super().validate_params(params)
        if merged["integrator"] not in INTEGRATORS:
            raise ControllerError(
                f"{self.name}: integrator must be one of {INTEGRATORS}, "
                f"got {merged['integrator']!r}"
            )
        substeps = merged["substeps"]
        if isinstance(substeps, bool) or not isinstance(substeps, int) or substeps < 1:
            raise ControllerError(f"{self.name}: substeps must be an int >= 1, got {substeps!r}")
        return merged

    @abstractmethod
    def derivative(
        self, t: float, x: np.ndarray, u: np.ndarray, y: np.ndarray, params: Mapping[str, Any]
    ) -> np.ndarray:
        """``dx_hat/dt`` at time ``t`` [s] (per second)."""

    @abstractmethod
    def output(
        self, t: float, x: np.ndarray, u: np.ndarray, y: np.ndarray, params: Mapping[str, Any]
    ) -> np.ndarray:
        """The next input ``u_{k+1}`` from the state at the end of the tick."""

    def step(
        self, tick: TickInput, x_hat: np.ndarray, params: Mapping[str, Any]
    ) -> tuple[np.ndarray, np.ndarray]:
        def rate(t: float, x: np.ndarray) -> np.ndarray:
            dx = np.asarray(self.derivative(t, x, tick.u, tick.y, params), dtype=np.float64)
            if dx.shape != x.shape:
                raise ControllerError(
                    f"{self.name}.derivative must return shape {x.shape}, got {dx.shape}"
                )
            return dx

        x = integrate(
            rate, tick.t, x_hat, tick.dt, method=params["integrator"], substeps=params["substeps"]
        )
        return self.output(tick.t + tick.dt, x, tick.u, tick.y, params), x


class ContinuousStateSpace(ContinuousModel):
    """``dx_hat/dt = A x_hat + B w``, ``u_{k+1} = C x_hat_{k+1} + D w`` with ``w = [u_k; y_k]``.

    Parameters: ``A``, ``B``, ``C``, ``D``, ``x0`` as in :class:`DiscreteStateSpace` (but ``A``
    and ``B`` are continuous-time, per second), plus ``integrator`` and ``substeps``.
    """

    default_params: ClassVar[Mapping[str, Any]] = {
        **ContinuousModel.default_params,
        **DiscreteStateSpace.default_params,
    }

    def validate_params(self, params: Mapping[str, Any]) -> dict[str, Any]:
        merged = super().validate_params(params)
        matrices = DiscreteStateSpace().validate_params(
            {key: merged[key] for key in DiscreteStateSpace.default_params}
        )
        merged.update(matrices)
        return merged

    def initial_state(self, params: Mapping[str, Any]) -> np.ndarray:
        return np.array(params["x0"], dtype=np.float64)

    def _w(self, u: np.ndarray, y: np.ndarray, params: Mapping[str, Any]) -> np.ndarray:
        m = params["D"].shape[0]
        p = params["D"].shape[1] - m
        return np.concatenate([_check_vector(self, "u_k", u, m), _check_vector(self, "y_k", y, p)])

    def derivative(
        self, t: float, x: np.ndarray, u: np.ndarray, y: np.ndarray, params: Mapping[str, Any]
    ) -> np.ndarray:
        return params["A"] @ x + params["B"] @ self._w(u, y, params)

    def output(
        self, t: float, x: np.ndarray, u: np.ndarray, y: np.ndarray, params: Mapping[str, Any]
    ) -> np.ndarray:
        return params["C"] @ x + params["D"] @ self._w(u, y, params)
