"""The lifecycle of one agent process, as a state machine.

::

    starting -> connected -> configured -> armed -> running <-> paused
                                                    ^  |
                                     board link back |  v board link fault
                                                    degraded
        (any state but stopped) --- fault / estop / low battery ---> safe -> stopped

* ``starting``: the process is up, nothing opened yet.
* ``connected``: the bus session is open.
* ``configured``: vehicle built, board connected, controller ready.
* ``armed``: publishers/subscribers declared, liveliness token up; waiting for the run to
  start: the first tick message, or (self-clocked) the schedule, which comes before tick 0.
* ``running``: answering ticks. ``paused``: no ticks, last input held.
* ``degraded``: the board link failed (stalled or unplugged board); the agent is reconnecting,
  its ticks are missed (reported as skipped) and its bus session stays up. Back to
  ``running`` once the link is re-established and configured, or ``safe`` past the link's
  timeout.
* ``safe``: the vehicle is in safe mode (outputs at their safe values); the agent still senses
  and answers ticks so the swarm's bookkeeping goes on, but never actuates again.
* ``stopped``: final; the process exits.

Every transition is reported to the listener given to the machine (the agent publishes it on
its status key, and the orchestrator records it on ``/<agent>/status``).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from statemachine import State, StateMachine

#: Called after every transition with (event, source state id, target state id, detail).
TransitionListener = Callable[[str, str, str, str], None]


class AgentLifecycle(StateMachine):
    """States and transitions of an agent process.

    Args:
        on_transition: called after every transition with ``(event, source, target, detail)``;
            ``detail`` is the ``detail=`` keyword given to the event (a reason), or ``""``.
    """

    starting = State(initial=True)
    connected = State()
    configured = State()
    armed = State()
    running = State()
    paused = State()
    degraded = State()
    safe = State()
    stopped = State(final=True)

    connect = starting.to(connected)
    configure = connected.to(configured)
    arm = configured.to(armed)
    start = armed.to(running)
    pause = running.to(paused)
    resume = paused.to(running)
    #: the board link failed; the agent reconnects.
    degrade = running.to(degraded)
    #: the board link is back and configured again.
    recover = degraded.to(running)
    #: fault, e-stop, low battery, lost board: outputs to safe values.
    enter_safe = (
        starting.to(safe)
        | connected.to(safe)
        | configured.to(safe)
        | armed.to(safe)
        | running.to(safe)
        | paused.to(safe)
        | degraded.to(safe)
    )
    #: orderly end: only from safe, so outputs are always made safe first.
    stop = safe.to(stopped)

    def __init__(self, on_transition: TransitionListener | None = None) -> None:
        self._on_transition = on_transition
        self._state_id = "starting"
        super().__init__()

    @property
    def state_id(self) -> str:
        """Id of the current state (``"starting"``, ..., ``"stopped"``)."""
        return self._state_id

    def after_transition(self, event: str, source: State, target: State, **kwargs: Any) -> None:
        """Remember the new state and tell the listener."""
        self._state_id = target.id
        if self._on_transition is not None and source is not target:
            self._on_transition(str(event), source.id, target.id, str(kwargs.get("detail", "")))


#: Transition events in the order a healthy agent goes through them.
STARTUP_EVENTS: tuple[str, ...] = ("connect", "configure", "arm", "start")
