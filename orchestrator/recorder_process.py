"""The recorder process: writes a run's MCAP file beside the instance manager, off its tick.

``hilswarm run`` starts ``python -m hilswarm.orchestrator.recorder_process`` with a pipe on
its standard input. The first message on the pipe says what to record (file, experiment as
loaded, log time of ``/experiment``); everything after it is the manager's record stream
(:mod:`hilswarm.orchestrator.record_stream`: an MCAP stream in numbered batches, read by a
:class:`~hilswarm.orchestrator.stream_recorder.StreamRecorder`). The process writes
``/experiment``, each vehicle's calibration and output names
(:func:`~hilswarm.orchestrator.recorder.record_vehicles`), says ``ready`` on its standard
output, then records every batch. JSON encoding and MCAP chunking happen here, on the other
core, never under the manager's GIL.

Recording is not on the real-time path. The process lowers its own CPU priority by
:data:`RECORDER_NICE` (+10), its niceness and its session's autogroup's
(:func:`~hilswarm.orchestrator.cpu_priority.lower_own_priority`: with autogroup scheduling a
niceness alone does not count against the agents, each in a session of its own), so the agents
and the manager win the CPU when the cores are busy and the recorder catches up when they idle.
The manager never waits for it: :meth:`RecorderProcess.write` queues the batch and returns, a
thread moves the queue into the pipe. Only when :data:`DEFAULT_QUEUE_BYTES` of records wait
does ``write`` wait too (logged once): records are never dropped while a recorder lives.

Nothing is lost when the recorder dies. The process finishes its MCAP chunk at batch
boundaries (at least every :data:`ACK_PERIOD_S`) and then *acknowledges* the last batch it
holds on disk (``ack N`` on its standard output). :class:`RecorderProcess` keeps every batch
until it is acknowledged. If the process dies (killed, crashed), a new one is started on the
next *segment* of the recording (``run.mcap``, ``run.1.mcap``, ``run.2.mcap``, ...: each a
complete MCAP file with ``/experiment`` and the calibrations) and is sent the stream's
definitions (its Header, Schema and Channel records so far) and then the unacknowledged
batches, so the new segment continues where the last chunk on disk ended. The dead
segment is rewritten as a complete file at the end (``hilswarm recover``'s reading). Only a
failure that a restart cannot mend ends the recording: the disk is full (``ENOSPC`` or
``EDQUOT`` only, :func:`~hilswarm.orchestrator.output_paths.is_no_space`; the process says
``error nospace``), or :data:`MAX_RESTARTS` restarts were used up. Then the owner's
``on_failure`` is called (``hilswarm run`` applies ``on_recording_failure``) and the records
from there on are counted as lost (:meth:`RecorderProcess.report`).

A run that fails before its first tick leaves no file: with ``staged=True`` the process writes
to a hidden name beside the file, :meth:`RecorderProcess.publish` gives it its name when the
run begins, and :meth:`RecorderProcess.close` removes a file that was never published.

End of the recording: the manager closes the pipe after its last batch; the process records
what is left and closes the file (summary, indexes, footer). The process runs in its own
session, so a Ctrl-C at the terminal reaches only the orchestrator, which then stops the run in
order. If the orchestrator is killed, the pipe closes too and the file is still closed
properly (with what reached the pipe).
"""

from __future__ import annotations

import contextlib
import fcntl
import logging
import os
import pickle
import select
import signal
import struct
import subprocess
import sys
import threading
import time
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType
from typing import IO, Any

from hilswarm.agents.errors import RecordingError
from hilswarm.agents.mcap_io import DEFAULT_COMPRESSION
from hilswarm.orchestrator.cpu_priority import PriorityError, lower_own_priority
from hilswarm.orchestrator.experiment import Experiment
from hilswarm.orchestrator.output_paths import is_no_space, watch_writer_errors
from hilswarm.orchestrator.record_stream import definitions
from hilswarm.orchestrator.recorder import Recorder, record_vehicles
from hilswarm.orchestrator.recorder_spawn import start_recorder_process
from hilswarm.orchestrator.run_summary import RecordingReport
from hilswarm.orchestrator.segments import existing_segments, segment_path
from hilswarm.orchestrator.stream_recorder import StreamRecorder

logger = logging.getLogger(__name__)

#: Pipe capacity asked for [bytes] (at most ``/proc/sys/fs/pipe-max-size``): about a second of
#: records of 64 agents at 200 Hz.
PIPE_SIZE = 1 << 20
#: Records the manager keeps in memory while the recorder lags behind [bytes]: some 50 s of
#: 32 agents at 100 Hz. Beyond it :meth:`RecorderProcess.write` waits (nothing is dropped).
DEFAULT_QUEUE_BYTES = 32 << 20
#: Niceness the recorder process adds to its own and sets on its session's autogroup
#: (:func:`~hilswarm.orchestrator.cpu_priority.lower_own_priority`): recording is not on the
#: real-time path, so the agents and the manager win the CPU when the cores are busy.
RECORDER_NICE = 10
#: Bound on waiting for the process to be ready (file created, vehicles described) [s].
DEFAULT_READY_TIMEOUT_S = 60.0
#: Bound on waiting for the process to finish the file after the pipe closed [s].
DEFAULT_CLOSE_TIMEOUT_S = 60.0
#: The recorder finishes its chunk and acknowledges at least this often while batches come [s]
#: (what a restarted recorder has to be sent again).
ACK_PERIOD_S = 0.25
#: Restarts of a dead recorder process in one run before the recording is given up.
MAX_RESTARTS = 3
#: Exit status of a recorder process whose disk is full.
EXIT_NO_SPACE = 3

_LENGTH = struct.Struct("<I")
#: Bytes read from the pipe at once [bytes].
_READ_SIZE = 1 << 20
_F_SETPIPE_SZ = getattr(fcntl, "F_SETPIPE_SZ", 1031)
_F_GETPIPE_SZ = getattr(fcntl, "F_GETPIPE_SZ", 1032)
_PIPE_MAX_SIZE = Path("/proc/sys/fs/pipe-max-size")
_MIN_PIPE_SIZE = 64 * 1024
_READY = b"ready"
#: ``ready live <ws:// URL>``: ready, and serving the live view there.
_LIVE = b"live"
_ACK = b"ack"
_ERROR = b"error"


def _enlarge_pipe(fd: int, size: int) -> int:
    """Ask for a pipe of ``size`` bytes (bounded by the system's maximum); returns its size.

    A smaller pipe only means earlier back-pressure: when the kernel refuses (the user's pipe
    pages are used up), smaller sizes are tried down to 64 KiB, the usual default.
    """
    with contextlib.suppress(OSError, ValueError):
        size = min(size, int(_PIPE_MAX_SIZE.read_text()))
    while size >= _MIN_PIPE_SIZE:
        try:
            return fcntl.fcntl(fd, _F_SETPIPE_SZ, size)
        except OSError:
            size //= 2
    try:
        return fcntl.fcntl(fd, _F_GETPIPE_SZ)
    except OSError:
        return 0


@dataclass
class _Batch:
    seq: int
    data: bytes
    count: int  # records (messages) in it
    tick: int  # the manager's tick when it was handed over (-1: unknown)
    first_tick: int  # the earliest tick its records can be of (-1: unknown)


def _signal_text(code: int | None) -> str:
    if code is None:
        return "did not exit"
    if code < 0:
        try:
            return f"was killed by {signal.Signals(-code).name}"
        except ValueError:
            return f"was killed by signal {-code}"
    return f"exited with status {code}"


class RecorderProcess:
    """The recorder process of one run, seen from the orchestrator (a :class:`RecordSink`).

    :meth:`write` never waits for the recorder: a thread of this object hands the records to
    the process's pipe, and up to ``queue_bytes`` of them wait in memory while the recorder
    lags behind (it runs at a lower CPU priority, :data:`RECORDER_NICE`). Only beyond that
    bound does :meth:`write` wait, once logged. A dead process is replaced (a new segment of
    the recording) and given the batches it had not acknowledged: nothing is dropped unless the
    recording cannot go on (disk full, restarts used up), which ``on_failure`` is told.

    Args:
        path: the MCAP file to write.
        experiment: the experiment as run (after command-line overrides).
        log_time_ns: log time of ``/experiment`` [ns, wall clock, Unix epoch].
        chunk_size: MCAP chunk size [bytes]; ``None`` (default): a chunk ends where the
            process acknowledges (so a new segment repeats nothing the dead one kept).
        compression: MCAP chunk compression (``"zstd"``, ``"lz4"`` or ``"none"``).
        queue_bytes: records kept in memory while the pipe is full or not acknowledged [bytes].
        python: interpreter to run the recorder with.
        staged: write under a hidden name until :meth:`publish` (a run that never starts
            leaves no file).
        on_failure: called once (from a thread of this object) with the reason when the
            recording cannot go on.
        max_restarts: restarts of a dead process before the recording is given up.
        live_port: serve the run live on this localhost port (0: a free one; ``None``: no
            live view), see :mod:`hilswarm.orchestrator.live_view`. A restarted process
            serves on the port the first one chose.
        process: a recorder process already started (:func:`start_recorder_process`), used
            as the first one: ``hilswarm run`` starts it before its own imports, so the
            process imports (~1 s) meanwhile; it waits for its set-up on its pipe. From here
            this object owns it.

    Call :meth:`wait_ready` before the first tick and :meth:`close` on every exit path.
    """

    def __init__(
        self,
        path: str | Path,
        experiment: Experiment,
        *,
        log_time_ns: int,
        chunk_size: int | None = None,
        compression: str = DEFAULT_COMPRESSION,
        queue_bytes: int = DEFAULT_QUEUE_BYTES,
        python: str = sys.executable,
        staged: bool = False,
        on_failure: Callable[[str], None] | None = None,
        max_restarts: int = MAX_RESTARTS,
        live_port: int | None = None,
        process: subprocess.Popen[bytes] | None = None,
    ) -> None:
        if queue_bytes < 1:
            raise RecordingError(f"queue_bytes must be positive [bytes], got {queue_bytes}")
        self.path = Path(path)
        self._experiment = experiment
        self._log_time_ns = int(log_time_ns)
        self._chunk_size = chunk_size
        self._compression = str(compression)
        self._python = python
        self._on_failure = on_failure
        self._max_restarts = max_restarts
        self._live_port = live_port
        #: The live view's ``ws://`` URL once :meth:`wait_ready` returned ("" without one).
        self.live_url = ""
        self._published = not staged
        self._staging = (
            self.path.with_name(f".{self.path.name}.starting-{os.getpid()}") if staged else None
        )
        self._changed = threading.Condition(threading.Lock())
        self._queue_bytes = queue_bytes
        self._queue: deque[_Batch] = deque()  # not yet in the pipe
        self._sent: deque[_Batch] = deque()  # in the pipe, not acknowledged
        self._queued = 0  # bytes in both
        self._seq = 0  # the last batch's number
        # The stream's Header, Schema and Channel records so far: a new process gets them first.
        self._definitions = b""
        self._tick = -1  # the latest tick a batch came with
        self._closing = False
        self._stdin_closed = False
        self._finished = False
        self._failed = ""
        self._broken = False  # the pipe of the current process broke
        self._ready = threading.Event()
        self._waited = False  # write() waited for room once (logged once)
        self._segments: list[Path] = [self.path]
        self._dead_segments: list[Path] = []
        self._failures: list[str] = []
        self._lost_records = 0
        self._lost_ticks: tuple[int, int] | None = None
        self._stopped_at_tick: int | None = None
        self._exit_code: int | None = None
        self.bytes_written = 0
        self.write_waits = 0
        self.restarts = 0
        self.resent_records = 0
        self._setups: dict[int, bytes] = {}  # set-up message of each process started
        self._generation = -1
        first = self._spawn(self._staging or self.path, process)
        with self._changed:
            self._install(first)
        self.pipe_size = _enlarge_pipe(self._fd, PIPE_SIZE)
        self._writer = threading.Thread(
            target=self._hand_over, name=f"recorder pipe {self.path.name}", daemon=True
        )
        self._reader = threading.Thread(
            target=self._listen, name=f"recorder acks {self.path.name}", daemon=True
        )
        self._writer.start()
        self._reader.start()

    # -- the process -------------------------------------------------------------------------

    def _install(self, process: subprocess.Popen[bytes]) -> None:
        """Make ``process`` the current one (call with the lock held)."""
        stdin = process.stdin
        if stdin is None:  # pragma: no cover
            raise RecordingError("the recorder process has no pipes")
        self.process = process
        self._fd = stdin.fileno()
        self._setup = self._setups.pop(process.pid)
        self._generation += 1
        self._broken = False
        self._stdin_closed = False
        self._changed.notify_all()

    def _spawn(
        self, path: Path, process: subprocess.Popen[bytes] | None = None
    ) -> subprocess.Popen[bytes]:
        """Start a recorder process on ``path`` (or give ``process``, already started, its
        set-up); :meth:`_install` makes it the current one."""
        setup = pickle.dumps(
            {
                "path": str(path),
                "experiment": self._experiment,
                "log_time_ns": self._log_time_ns,
                "chunk_size": self._chunk_size,
                "compression": self._compression,
                "live_port": self._live_port,
            }
        )
        if process is None:
            process = start_recorder_process(self._python)
        self._setups[process.pid] = _LENGTH.pack(len(setup)) + setup
        return process

    def wait_ready(self, timeout_s: float = DEFAULT_READY_TIMEOUT_S) -> None:
        """Block until the file is created and the run's start is recorded.

        Raises:
            RecordingError: the process failed (e.g. the file cannot be created) or timed out.
        """
        deadline = time.monotonic() + timeout_s
        while not self._ready.wait(timeout=0.05):
            if self._failed or self._finished:
                raise RecordingError(
                    f"the recorder process for {self.path} {self._failed or 'ended'}; "
                    "see its log above"
                )
            if time.monotonic() > deadline:
                raise RecordingError(
                    f"the recorder process for {self.path} did not answer within {timeout_s} s"
                )

    def publish(self, *, replace: bool = False) -> None:
        """Give a staged recording its name (the run begins). Idempotent.

        Args:
            replace: replace an existing file of that name (and remove the stale segments of
                an older recording beside it); otherwise an existing file is an error.

        Raises:
            RecordingError: the file exists and ``replace`` is false, or it cannot be renamed.
        """
        with self._changed:
            if self._published or self._staging is None:
                self._published = True
                return
            try:
                if replace:
                    for stale in existing_segments(self.path)[1:]:
                        stale.unlink()
                    os.replace(self._staging, self.path)
                else:
                    os.link(self._staging, self.path)  # refuses to replace, unlike rename
                    os.unlink(self._staging)
            except FileExistsError as exc:
                raise RecordingError(
                    f"{self.path} exists; it is not replaced (use --force to replace it)"
                ) from exc
            except OSError as exc:
                raise RecordingError(f"cannot name the recording {self.path}: {exc}") from exc
            self._published = True

    def _listen(self) -> None:
        """The reader thread: acknowledgements, errors and the end of each process."""
        while True:
            process = self.process
            stdout = process.stdout
            error = ""
            if stdout is not None:
                for line in stdout:
                    word, _, rest = line.strip().partition(b" ")
                    if word == _ACK:
                        self._acknowledge(int(rest))
                    elif word == _READY:
                        self._on_ready(rest)
                    elif word == _ERROR:
                        error = rest.decode(errors="replace")
                stdout.close()
            code = process.wait()
            if not self._ended(process, code, error):
                return

    def _on_ready(self, rest: bytes) -> None:
        """``ready`` or ``ready live <URL>``: keep the URL and its port (for a restart)."""
        word, _, url = rest.strip().partition(b" ")
        if word == _LIVE and url:
            self.live_url = url.decode()
            port = self.live_url.rsplit(":", 1)[-1].strip("/")
            if port.isdigit():
                self._live_port = int(port)
        self._ready.set()

    def _acknowledge(self, seq: int) -> None:
        with self._changed:
            sent = self._sent
            while sent and sent[0].seq <= seq:
                batch = sent.popleft()
                self._queued -= len(batch.data)
                self.bytes_written += len(batch.data)
            self._changed.notify_all()

    def _ended(self, process: subprocess.Popen[bytes], code: int, error: str) -> bool:
        """A process ended; returns True when a new one was started (keep listening)."""
        failure = ""
        with self._changed:
            self._exit_code = code
            if code == 0 and self._closing and self._stdin_closed:
                self._finished = True
                self._changed.notify_all()
                return False
            segment = self._segments[-1]
            what = f"the recorder process of {segment.name} {_signal_text(code)}"
            if error:
                what += f" ({error})"
            tick = self._tick
            at = f" at tick {tick}" if tick >= 0 else ""
            no_space = code == EXIT_NO_SPACE or error.startswith("nospace")
            started = self._published and self._ready.is_set()
            if no_space or not started or self.restarts >= self._max_restarts:
                why = "the disk is full" if no_space else (
                    "restarts used up" if started else "before the run began"
                )  # fmt: skip
                failure = f"{what}{at}; recording stopped: {why}"
                if started:
                    self._dead_segments.append(segment)  # rewritten complete at close
                self._give_up(failure)
            else:
                self.restarts += 1
                self._dead_segments.append(segment)
                resent = sum(batch.count for batch in self._sent)
                new = segment_path(self.path, len(self._segments))
                self._segments.append(new)
                self._queue.extendleft(reversed(self._sent))
                self._sent.clear()
                # No batch goes to the dead process's pipe while the new one starts (outside
                # the lock, below): a batch written there would sit in _sent, never reach the
                # new process, and be taken as acknowledged by its first acknowledgement.
                self._broken = True
                self.resent_records += resent
                self._failures.append(
                    f"{what}{at}; continued in {new.name} ({resent} records sent again)"
                )
                logger.warning("%s; continuing in %s", what, new)
        if not failure:  # start the new process outside the lock: write() never waits for it
            try:
                replacement = self._spawn(new)
            except OSError as exc:
                failure = f"{what}{at}; recording stopped: no new recorder process: {exc}"
                with self._changed:
                    self._give_up(failure)
            else:
                _enlarge_pipe(replacement.stdin.fileno(), PIPE_SIZE)  # type: ignore[union-attr]
                with self._changed:
                    self._install(replacement)
                return True
        logger.error("%s", failure)
        if self._on_failure is not None:
            self._on_failure(failure)
        return False

    def _give_up(self, failure: str) -> None:
        """The recording cannot go on: count what is lost (call with the lock held)."""
        self._failed = failure
        self._failures.append(failure)
        pending = list(self._sent) + list(self._queue)
        self._sent.clear()
        self._queue.clear()
        self._queued = 0
        # every tick before the first batch not acknowledged is on disk; from there on the
        # records may be missing (the first of them may have reached the file unacknowledged)
        first = min((b.first_tick for b in pending if b.first_tick >= 0), default=self._tick)
        self._stopped_at_tick = max(first, 0) if self._published else None
        for batch in pending:
            self._count_lost(batch.count, batch.first_tick, batch.tick)
        self._changed.notify_all()

    def _count_lost(self, count: int, first_tick: int, tick: int) -> None:
        """``count`` records of ticks ``first_tick..tick`` are lost (``tick`` -1: unknown ticks;
        ``first_tick`` as :meth:`write` settles it: known whenever ``tick`` is)."""
        if not count:
            return
        self._lost_records += count
        if tick >= 0:
            first, last = self._lost_ticks or (first_tick, tick)
            self._lost_ticks = (min(first, first_tick), max(last, tick))

    # -- writing -----------------------------------------------------------------------------

    def write(
        self,
        data: bytes,
        *,
        seq: int,
        count: int = 0,
        tick: int = -1,
        first_tick: int = -1,
        defines: bool = False,
    ) -> None:
        """Hand batch ``seq`` of the record stream to the process; returns at once unless the
        queue is full.

        Args:
            data: whole MCAP records of the stream, the last its batch marker.
            seq: the batch's number (increasing; the process acknowledges by it).
            count: records in ``data`` (for the count of lost records, should any be lost).
            tick: the manager's tick when the batch was made (-1: unknown).
            first_tick: the earliest tick its records can be of (the manager's tick when it
                began gathering them; -1: ``tick``). What is reported lost counts from here.
            defines: ``data`` holds Schema or Channel records (kept for a new process).

        While ``queue_bytes`` of records wait for the pipe or an acknowledgement, this waits
        for room (logged once: the recorder cannot keep up); a batch larger than the bound
        waits for an empty queue. After the recording failed, records are counted as lost.
        """
        if not data:
            return
        changed = self._changed
        with changed:
            first = min(first_tick, tick) if first_tick >= 0 else tick
            self._tick = max(self._tick, tick)
            if self._failed:
                self._count_lost(count, first, tick)
                return
            if self._queued and self._queued + len(data) > self._queue_bytes:
                self.write_waits += 1
                if not self._waited:
                    self._waited = True
                    logger.warning(
                        "the recorder process of %s lags behind by %.1f MiB of records: "
                        "the run waits for it (nothing is dropped)",
                        self.path,
                        self._queued / 2**20,
                    )
                while self._queued and self._queued + len(data) > self._queue_bytes:
                    if self._failed:
                        self._count_lost(count, first, tick)
                        return
                    changed.wait(1.0)
            if self._closing:
                logger.error(
                    "%d bytes of records for %s came after the recorder was closed: not recorded",
                    len(data),
                    self.path,
                )
                self._count_lost(count, first, tick)
                return
            if seq <= self._seq:
                raise RecordingError(f"record batch {seq} after batch {self._seq}")
            self._seq = seq
            if defines:
                self._definitions += definitions(data)
            self._queue.append(_Batch(seq, bytes(data), count, tick, first))
            self._queued += len(data)
            changed.notify_all()

    def _hand_over(self) -> None:
        """The writer thread: move queued batches into the pipe of the current process."""
        changed = self._changed
        generation = -1
        stdin: IO[bytes] | None = None
        while True:
            with changed:
                while True:
                    if self._failed or self._finished:
                        return
                    if not self._broken:
                        if generation != self._generation or self._queue:
                            break  # a new process (its set-up message first), or batches
                        if self._closing and not self._stdin_closed:
                            self._close_stdin()  # the process acknowledges the rest at its end
                    changed.wait()
                parts: list[bytes] = []
                if generation != self._generation:
                    if stdin is not None:  # the dead process's pipe: only this thread writes it
                        with contextlib.suppress(OSError):
                            stdin.close()
                    generation = self._generation
                    stdin = self.process.stdin
                    # its set-up, then the stream's definitions so far (a new segment's first
                    # batch may be any), then the batches
                    parts += (self._setup, self._definitions)
                while self._queue:
                    batch = self._queue.popleft()
                    self._sent.append(batch)
                    parts.append(batch.data)
                fd = self._fd
            try:
                view = memoryview(b"".join(parts))
                while view:
                    written = os.write(fd, view)
                    view = view[written:]
            except OSError as exc:  # BrokenPipeError: the process died; the reader restarts it
                with changed:
                    if generation == self._generation:
                        self._broken = True
                logger.debug("the recorder pipe of %s broke: %s", self.path, exc)

    def _close_stdin(self) -> None:
        """Close the current process's pipe: it finishes the file (call with the lock held)."""
        self._stdin_closed = True
        stdin = self.process.stdin
        if stdin is not None:
            with contextlib.suppress(OSError):
                stdin.close()

    @property
    def queued_bytes(self) -> int:
        """Records handed to :meth:`write` and not yet acknowledged by the recorder [bytes]."""
        return self._queued

    def wait_written(self, timeout_s: float) -> bool:
        """Wait (bounded by ``timeout_s`` [s]) until every record handed to :meth:`write` is
        acknowledged, i.e. written to the file; ``False`` on timeout or a failed recording.

        A recorder behind the ticks (niced, on full CPUs) catches up here; the file stays
        open (:meth:`close` ends it).
        """
        with self._changed:
            written = self._changed.wait_for(lambda: self._queued <= 0 or self._failed, timeout_s)
            return bool(written) and not self._failed

    @property
    def failed(self) -> str:
        """Why the recording cannot go on ("" while all is well)."""
        return self._failed

    @property
    def segments(self) -> list[Path]:
        """The files of this recording so far, in order."""
        return list(self._segments)

    def report(self) -> RecordingReport:
        """What happened to the recording (for the run's summary)."""
        with self._changed:
            return RecordingReport(
                segments=[str(path) for path in self._segments],
                failures=list(self._failures),
                lost_records=self._lost_records,
                lost_ticks=self._lost_ticks,
                stopped_at_tick=self._stopped_at_tick,
            )

    def close(self, timeout_s: float = DEFAULT_CLOSE_TIMEOUT_S) -> int | None:
        """End the stream; wait (bounded) for the file to be closed. Returns the exit status.

        The records still queued are handed over first (to a restarted process if need be).
        Idempotent. A process that does not finish in time is killed. Segments whose process
        died are rewritten as complete files; a staged recording never published is removed.

        Raises:
            RecordingError: the hidden file of a recording never published cannot be removed
                (the process has ended all the same).
        """
        deadline = time.monotonic() + timeout_s
        with self._changed:
            self._closing = True
            self._changed.notify_all()
            while not (self._finished or self._failed):
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    break
                self._changed.wait(min(remaining, 0.5))
            finished = self._finished or self._failed
        if not finished:
            logger.error("the recorder process of %s did not finish; killing it", self.path)
            with self._changed:
                self._max_restarts = self.restarts  # no restart of a process killed here
            with contextlib.suppress(ProcessLookupError):
                self.process.kill()
        self._reader.join(timeout=max(1.0, deadline - time.monotonic()))
        self._writer.join(timeout=1.0)
        code = self.process.poll() if self._exit_code is None else self._exit_code
        if code is None:
            with contextlib.suppress(subprocess.TimeoutExpired):
                code = self.process.wait(timeout=10)
        if code != 0:
            logger.error("the recorder process of %s %s", self.path, _signal_text(code))
        if not self._published and self._staging is not None:
            self._remove_staging()
        else:
            self._mend_dead_segments()
        return code

    def _remove_staging(self) -> None:
        """Remove the hidden file of a recording never published (if it was created).

        Raises:
            RecordingError: it exists and cannot be removed.
        """
        staging = self._staging
        if staging is None or not (staging.exists() or staging.is_symlink()):
            return  # never created (its folder may not even be writable: no unlink to fail)
        try:
            staging.unlink()
        except FileNotFoundError:
            return
        except OSError as exc:
            raise RecordingError(
                f"cannot remove the unfinished recording {staging}: {exc.strerror or exc}"
            ) from exc

    def _mend_dead_segments(self) -> None:
        """Rewrite the segments whose process died as complete MCAP files (best effort)."""
        from hilswarm.orchestrator.recover import recover  # noqa: PLC0415 - rare

        for segment in self._dead_segments:
            try:
                recover(segment, in_place=True)
            except (RecordingError, OSError) as exc:
                logger.error(
                    "%s could not be rewritten (%s): run `hilswarm recover %s`",
                    segment,
                    exc,
                    segment,
                )
        self._dead_segments.clear()

    def __enter__(self) -> RecorderProcess:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()


# -- the process side ------------------------------------------------------------------------


def _read_exactly(fd: int, size: int) -> bytes | None:
    """``size`` bytes from ``fd``; ``None`` at the end of the stream before any of them.

    Raises:
        RecordingError: the stream ended inside the requested bytes.
    """
    parts: list[bytes] = []
    wanted = size
    while wanted:
        data = os.read(fd, wanted)
        if not data:
            if wanted == size:
                return None
            raise RecordingError(f"the record stream ended {wanted} bytes short of a message")
        parts.append(data)
        wanted -= len(data)
    return b"".join(parts)


class DiskFullError(RecordingError):
    """The recording's disk (or quota) is full: a restarted recorder would fail too."""


def _say(out: IO[bytes], *words: bytes) -> None:
    out.write(b" ".join(words) + b"\n")
    out.flush()


def record_stream(fd: int, out: IO[bytes], *, clock: Callable[[], float] = time.monotonic) -> int:
    """Record the stream on ``fd`` until it ends; returns the number of messages recorded.

    Args:
        fd: the read end of the manager's pipe.
        out: a binary stream for ``ready`` (once recording has begun) and ``ack N`` (batch
            ``N`` and all before it are on disk).
        clock: monotonic clock [s] pacing the acknowledgements.
    """
    head = _read_exactly(fd, _LENGTH.size)
    if head is None:
        raise RecordingError("the record stream ended before its set-up message")
    (size,) = _LENGTH.unpack(head)
    body = _read_exactly(fd, size)
    if body is None:
        raise RecordingError("the record stream ended before its set-up message")
    setup = pickle.loads(body)  # our own parent process wrote it
    path = Path(setup["path"])
    with watch_writer_errors() as writer_errors:
        try:
            return _record(fd, out, setup, clock)
        except (RecordingError, OSError, RuntimeError) as exc:
            if is_no_space(exc):
                raise DiskFullError(f"{path}: {exc}") from exc
            if writer_errors.no_space:  # the writer said why before it failed
                raise DiskFullError(f"{path}: {exc} ({writer_errors.no_space})") from exc
            raise


def _record(fd: int, out: IO[bytes], setup: dict[str, Any], clock: Callable[[], float]) -> int:
    """:func:`record_stream` after the set-up message."""
    experiment: Experiment = setup["experiment"]
    log_time_ns: int = setup["log_time_ns"]
    path = Path(setup["path"])
    live = None
    if setup.get("live_port") is not None:
        from hilswarm.orchestrator.live_view import LiveView  # noqa: PLC0415 - only with --live

        live = LiveView(int(setup["live_port"]), name=f"hilswarm {experiment.name}")
    with contextlib.ExitStack() as stack:
        if live is not None:
            stack.callback(live.close)
        recorder = stack.enter_context(
            Recorder(
                path,
                experiment,
                chunk_size=setup["chunk_size"],
                compression=setup.get("compression", DEFAULT_COMPRESSION),
                log_time_ns=log_time_ns,
                mirror=live,
            )
        )
        record_vehicles(recorder, experiment, log_time_ns=log_time_ns)
        recorder.flush()
        if live is None:
            _say(out, _READY)
        else:
            _say(out, _READY, _LIVE, live.url.encode())
        stream = StreamRecorder(recorder, experiment)
        started = time.perf_counter()
        cpu_started = time.process_time()
        last_seq = acked = -1
        next_ack = clock() + ACK_PERIOD_S
        while True:
            if last_seq > acked:
                # acknowledge when due, or at once when the manager has nothing more now
                wait_s = max(0.0, next_ack - clock())
                if not select.select([fd], [], [], wait_s)[0]:
                    recorder.flush()
                    _say(out, _ACK, str(last_seq).encode())
                    acked = last_seq
                    next_ack = clock() + ACK_PERIOD_S
            data = os.read(fd, _READ_SIZE)
            if not data:
                break
            # only whole batches are recorded: what is on disk after a flush is theirs
            seq = stream.feed(data)
            if seq is None:
                continue
            last_seq = seq
            if clock() >= next_ack:
                recorder.flush()
                _say(out, _ACK, str(seq).encode())
                acked = seq
                next_ack = clock() + ACK_PERIOD_S
        stream.feed(b"", whole=True)  # the stream's end, or what came before the pipe closed
        if stream.pending:
            logger.error("record stream ended inside a record (%d bytes lost)", stream.pending)
        logger.info(
            "recorded %d stream messages (%d bad, %d messages written) in %.2f s (%.2f s CPU) "
            "to %s",
            stream.messages,
            stream.errors,
            recorder.message_count,
            time.perf_counter() - started,
            time.process_time() - cpu_started,
            path,
        )
    if last_seq > acked:
        _say(out, _ACK, str(last_seq).encode())
    return stream.messages


class _RepeatFilter(logging.Filter):
    """Shows each message of the foxglove SDK once: on a full disk it logs every message it
    could not write (hundreds a second); the repeats are counted instead."""

    #: Distinct messages remembered (beyond it, new ones are shown and not remembered).
    MAX_REMEMBERED = 100

    def __init__(self) -> None:
        super().__init__()
        self._seen: set[str] = set()
        self.repeats = 0

    def filter(self, record: logging.LogRecord) -> bool:
        if not record.name.startswith("foxglove"):
            return True
        text = record.getMessage()
        if text in self._seen:
            self.repeats += 1
            return False
        if len(self._seen) < self.MAX_REMEMBERED:
            self._seen.add(text)
        return True


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``python -m hilswarm.orchestrator.recorder_process``."""
    del argv
    logging.basicConfig(
        level=logging.WARNING, format="%(asctime)s %(levelname)s recorder %(name)s: %(message)s"
    )
    repeats = _RepeatFilter()
    for handler in logging.getLogger().handlers:
        handler.addFilter(repeats)
    try:
        return _main()
    finally:
        if repeats.repeats:
            logger.warning("%d repeated foxglove messages not shown", repeats.repeats)


def _main() -> int:
    """:func:`main` once logging is set up."""
    # Stopping is the orchestrator's job: it closes the pipe after the last record.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    # Not on the real-time path: let the agents and the manager have the CPU first.
    try:
        lower_own_priority(RECORDER_NICE)  # its session's autogroup too: it leads its session
    except PriorityError as exc:
        logger.warning("could not lower the recorder's CPU priority: %s", exc)
    out = sys.stdout.buffer
    try:
        record_stream(sys.stdin.fileno(), out)
    except DiskFullError as exc:
        logger.error("disk full: %s", exc)
        with contextlib.suppress(OSError):
            _say(out, _ERROR, b"nospace", str(exc).encode(errors="replace"))
        return EXIT_NO_SPACE
    except (RecordingError, OSError, RuntimeError, pickle.UnpicklingError, EOFError) as exc:
        logger.error("%s", exc)
        with contextlib.suppress(OSError):
            _say(out, _ERROR, str(exc).encode(errors="replace"))
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
