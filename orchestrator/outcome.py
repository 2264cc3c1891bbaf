"""The outcome of a run: its exit status and every degradation, with counts and ticks.

``hilswarm run`` exits with

* ``0`` — clean: every planned tick ran (or the run was stopped on request), no agent went
  safe or was lost, no tick was missed, late ticks at most ``max_late_fraction`` of the
  planned ticks, and the recording holds everything;
* ``3`` — completed but degraded: an agent went safe, was lost or reported a degraded link,
  ticks were missed, late ticks above ``max_late_fraction``, an e-stop, or the recording is
  incomplete or was split after a recorder failure;
* ``1`` — failed: the run could not do what was asked (an agent lost with
  ``on_agent_loss = "stop"``, an agent safe with ``on_agent_safe = "stop"``, an agent safe from
  its first tick, no tick completed, a start-up failure);
* ``2`` — bad input (the experiment file, command-line options; decided before the run);
* ``130`` — interrupted (Ctrl-C).

:func:`decide` is pure: it reads a :class:`~hilswarm.orchestrator.run_summary.RunSummary`.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from hilswarm.orchestrator.run_summary import RunSummary

CLEAN = 0
FAILED = 1
BAD_INPUT = 2
DEGRADED = 3
INTERRUPTED = 130

#: Agents named in one line of the summary (late answers, skipped ticks, agents sharing
#: counters); the rest are counted: one line, however many agents.
LISTED_AGENTS = 8
#: Agent status counters listed in the summary when non-zero (reported by the agents, see
#: docs/running.md): a count, or counts by key or reason.
COUNTER_NAMES = ("malformed", "dropped", "skipped", "link_faults", "stale_samples")
#: How each counter reads in the summary.
_COUNTER_WORDS = {
    "malformed": "malformed messages",
    "dropped": "dropped messages",
    "skipped": "ticks skipped",
    "link_faults": "link faults",
    "stale_samples": "stale samples (the XBee gateway answered from the robot's last samples)",
}
#: Counters of a mode's normal operation: listed as a note, never a degradation. STALE board
#: answers come only from the XBee gateway's broadcast mode, by design (docs/xbee.md).
BENIGN_COUNTERS = frozenset({"stale_samples"})
#: Reasons of dropped input that are normal under load (not a degradation by themselves).
BENIGN_DROPS = frozenset({"stale"})


@dataclass(frozen=True)
class Outcome:
    """The exit status of a run and why.

    Attributes:
        code: the exit status (:data:`CLEAN`, :data:`DEGRADED`, :data:`FAILED`,
            :data:`INTERRUPTED`).
        failures: why the run failed (empty unless ``code`` is :data:`FAILED`).
        degradations: every degradation, one line each, with counts and ticks.
        notes: facts worth knowing that do not degrade the run.
    """

    code: int
    failures: list[str] = field(default_factory=list)
    degradations: list[str] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)

    @property
    def word(self) -> str:
        """``clean``, ``degraded``, ``failed`` or ``interrupted``."""
        return {CLEAN: "clean", DEGRADED: "degraded", INTERRUPTED: "interrupted"}.get(
            self.code, "failed"
        )

    def text(self) -> str:
        """The outcome lines of the end-of-run summary."""
        lines = [f"outcome: {self.word} (exit status {self.code})"]
        lines += [f"  failed: {line}" for line in self.failures]
        lines += [f"  degraded: {line}" for line in self.degradations]
        lines += [f"  note: {line}" for line in self.notes]
        return "\n".join(lines)


def _counter_texts(counters: dict[str, int | dict[str, int]]) -> tuple[list[str], bool]:
    """Texts of an agent's non-zero counters, and whether any of them degrades the run."""
    parts: list[str] = []
    serious = False
    for key in COUNTER_NAMES:
        value = counters.get(key)
        if isinstance(value, dict):
            total = sum(value.values())
            shown = ", ".join(f"{reason}={count}" for reason, count in value.items() if count)
            text = f"{total} {_COUNTER_WORDS[key]} ({shown})"
            serious = serious or any(
                count and reason not in BENIGN_DROPS for reason, count in value.items()
            )
        else:
            total = int(value or 0)
            text = f"{total} {_COUNTER_WORDS[key]}"
            serious = serious or (total > 0 and key not in BENIGN_COUNTERS)
        if total:
            parts.append(text)
    return parts, serious


def _agents_text(names: list[str]) -> str:
    """``agent a``; ``agents a, b``; past :data:`LISTED_AGENTS` names, ``and N more``."""
    if len(names) == 1:
        return f"agent {names[0]}"
    more = len(names) - LISTED_AGENTS
    return f"agents {', '.join(names[:LISTED_AGENTS])}" + (f" and {more} more" if more > 0 else "")


def _counts_text(counts: dict[str, int]) -> str:
    """``a=3, b=1`` in the experiment's order; with more than :data:`LISTED_AGENTS` agents the
    ones with the highest counts and a count of the rest (the record has every agent's)."""
    items = list(counts.items())
    if len(items) > LISTED_AGENTS:
        items.sort(key=lambda item: -item[1])  # stable: experiment order among equal counts
    text = ", ".join(f"{name}={count}" for name, count in items[:LISTED_AGENTS])
    rest = items[LISTED_AGENTS:]
    if rest:
        text += f" and {sum(c for _, c in rest)} more from {len(rest)} other agents"
    return text


def _ticks(first: int, last: int) -> str:
    return f"tick {first}" if first == last else f"ticks {first}..{last}"


def decide(
    summary: RunSummary | None,
    *,
    error: str = "",
    interrupted: bool = False,
) -> Outcome:
    """The outcome of a run from its summary (``None``: it never started ticking).

    Args:
        summary: what the run did.
        error: a failure that ended the run (start-up failure, lost bus, ...).
        interrupted: the run was interrupted by Ctrl-C.
    """
    failures: list[str] = [error] if error else []
    degradations: list[str] = []
    notes: list[str] = []
    if summary is None:
        if not failures:
            failures.append("the run did not start")
        return Outcome(INTERRUPTED if interrupted else FAILED, failures)
    last_tick = max(summary.ticks_run - 1, 0)
    if summary.failed:
        failures.append(summary.stop_reason)
    for name, event in summary.safe.items():
        line = f"agent {name} safe from tick {event.tick}: {event.detail or 'no reason given'}"
        if event.tick <= 0:
            failures.append(f"{line} (safe from its first tick)")
        else:
            degradations.append(line)
    for name in summary.lost:
        event = summary.lost_at.get(name)
        if event is None:
            degradations.append(f"agent {name} lost")
            continue
        missed = max(summary.planned_ticks - event.tick, 0)
        end = min(summary.planned_ticks - 1, max(last_tick, event.tick))
        degradations.append(
            f"agent {name} lost at tick {event.tick}: {event.detail}; "
            f"{missed} ticks missed ({_ticks(event.tick, end)})"
            if missed
            else f"agent {name} lost at tick {event.tick}: {event.detail}"
        )
    for name, events in summary.degraded.items():
        ticks = ", ".join(str(event.tick) for event in events[:10])
        more = f" and {len(events) - 10} more" if len(events) > 10 else ""
        degradations.append(
            f"agent {name} degraded {len(events)} times (ticks {ticks}{more}): "
            f"{events[-1].detail or 'link fault'}"
        )
    late_fraction = summary.late_ticks / max(summary.planned_ticks, 1)
    tolerated = late_fraction <= summary.max_late_fraction
    # Agents with the same counters share a line; skipped ticks have one line of their own.
    same: dict[tuple[str, bool], list[str]] = {}
    skipped: dict[str, int] = {}
    for name, counters in summary.counters.items():
        skipped[name] = int(counters.get("skipped") or 0)
        others = {key: value for key, value in counters.items() if key != "skipped"}
        parts, serious = _counter_texts(others)
        if parts:
            same.setdefault((", ".join(parts), serious), []).append(name)
    for (text, serious), names in same.items():
        (degradations if serious else notes).append(f"{_agents_text(names)}: {text}")
    skipped = {name: count for name, count in skipped.items() if count}
    if skipped:
        # A skipped tick is a late tick of its agent (its y never came): within the tolerance
        # of late ticks a note like them, beyond it a degradation.
        line = f"ticks skipped by agents that fell behind: {_counts_text(skipped)}"
        (notes if tolerated else degradations).append(line)
    late = {name: count for name, count in summary.late.items() if count}
    if summary.late_ticks:
        where = summary.late_range()
        line = (
            f"{summary.late_ticks} of {summary.planned_ticks} ticks late ({late_fraction:.1%}, "
            f"max_late_fraction {summary.max_late_fraction:.1%}{'; ' + where if where else ''}"
            "); late answers: " + _counts_text(late)
        )
        if not tolerated:
            degradations.append(line)
        else:
            notes.append(line)
    if summary.estop_tick is not None:
        degradations.append(f"e-stop at tick {summary.estop_tick}")
    recording = summary.recording
    if recording is not None:
        degradations += [f"recording: {line}" for line in recording.failures]
        if recording.lost_records:
            span = ""
            if recording.lost_ticks:
                first, last = recording.lost_ticks
                # the manager's last batch carries the tick after the last one: no such tick
                last = max(first, min(last, last_tick))
                seconds = f", {(last - first + 1) * summary.dt_s:.2f} s" if summary.dt_s else ""
                span = f" ({_ticks(first, last)}{seconds})"
            # a recording given up: the records it had not acknowledged may be in the file
            bound = "at most " if recording.stopped_at_tick is not None else ""
            degradations.append(f"recording: {bound}{recording.lost_records} records lost{span}")
        elif recording.failures and recording.stopped_at_tick is None:
            notes.append("recording: no record lost (every segment is complete)")
        if recording.stopped_at_tick is not None:
            degradations.append(
                f"recording: stopped at tick {recording.stopped_at_tick}; "
                f"ticks {recording.stopped_at_tick}..{last_tick} are not recorded, or only in part"
            )
        if len(recording.segments) > 1:
            notes.append("recording in segments: " + ", ".join(recording.segments))
    complete = summary.stop_reason == "completed" or summary.stop_reason.startswith(
        "stop requested"
    )
    if summary.ticks == 0 and summary.planned_ticks > 0 and not interrupted:
        failures.append(
            f"no tick completed on time ({summary.late_ticks} late)"
            if summary.late_ticks
            else "no tick completed"
        )
    elif not complete and not failures and not interrupted and summary.estop_tick is None:
        degradations.append(
            f"stopped at tick {last_tick} of {summary.planned_ticks}: {summary.stop_reason}"
        )
    if interrupted:
        code = INTERRUPTED
    elif failures:
        code = FAILED
    elif degradations:
        code = DEGRADED
    else:
        code = CLEAN
    return Outcome(code, failures, degradations, notes)
