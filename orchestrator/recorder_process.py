"""The recorder process: writes a run's MCAP file beside the instance manager, off its tick.

``hilswarm run`` starts ``python -m hilswarm.orchestrator.recorder_process`` with a pipe on
its standard input. The first message on the pipe says what to record (file, experiment as
loaded, log time of ``/experiment``); everything after it is the manager's record stream
(:mod:`hilswarm.orchestrator.record_stream`). The process writes ``/experiment``, each
vehicle's calibration and output names (:func:`~hilswarm.orchestrator.recorder.record_vehicles`),
says ``ready`` on its standard output, then records every frame. JSON encoding and MCAP
chunking happen here, on the other core, never under the manager's GIL.

Recording is not on the real-time path. The process lowers its own CPU priority
(``os.nice(RECORDER_NICE)``, +10), so the agents and the manager win the CPU when the cores are
busy and the recorder catches up when they idle. The manager never waits for it:
:meth:`RecorderProcess.write` queues the batch and returns, a thread moves the queue into the
pipe (enlarged to :data:`PIPE_SIZE`, within ``/proc/sys/fs/pipe-max-size``). Only when
:data:`DEFAULT_QUEUE_BYTES` of records wait does ``write`` wait too (logged once): records are
never dropped while the recorder lives.

End of the recording: the manager closes the pipe after its last frame; the process records
what is left and closes the file (summary, indexes, footer). The process runs in its own
session, so a Ctrl-C at the terminal reaches only the orchestrator, which then stops the run in
order and closes the pipe (after handing over what is queued). If the orchestrator is killed,
the pipe closes too and the file is still closed properly (with what reached the pipe); if the
recorder itself is killed, ``hilswarm recover`` rewrites the file from its complete chunks.
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
from collections.abc import Sequence
from pathlib import Path
from types import TracebackType
from typing import Any

from hilswarm.agents.errors import RecordingError
from hilswarm.agents.mcap_io import DEFAULT_COMPRESSION
from hilswarm.orchestrator.experiment import Experiment
from hilswarm.orchestrator.record_stream import FrameReader, FrameRecorder
from hilswarm.orchestrator.recorder import DEFAULT_CHUNK_SIZE, Recorder, record_vehicles

logger = logging.getLogger(__name__)

#: Pipe capacity asked for [bytes] (at most ``/proc/sys/fs/pipe-max-size``): about a second of
#: records of 64 agents at 200 Hz.
PIPE_SIZE = 1 << 20
#: Records the manager keeps in memory while the recorder lags behind [bytes]: some 50 s of
#: 32 agents at 100 Hz. Beyond it :meth:`RecorderProcess.write` waits (nothing is dropped).
DEFAULT_QUEUE_BYTES = 32 << 20
#: Niceness the recorder process adds to its own (``os.nice``): recording is not on the
#: real-time path, so the agents and the manager win the CPU when the cores are busy.
RECORDER_NICE = 10
#: Bound on waiting for the process to be ready (file created, vehicles described) [s].
DEFAULT_READY_TIMEOUT_S = 60.0
#: Bound on waiting for the process to finish the file after the pipe closed [s].
DEFAULT_CLOSE_TIMEOUT_S = 60.0

_LENGTH = struct.Struct("<I")
_F_SETPIPE_SZ = getattr(fcntl, "F_SETPIPE_SZ", 1031)
_F_GETPIPE_SZ = getattr(fcntl, "F_GETPIPE_SZ", 1032)
_PIPE_MAX_SIZE = Path("/proc/sys/fs/pipe-max-size")
_MIN_PIPE_SIZE = 64 * 1024
_READY = b"ready\n"
_READY_LIVE = b"ready live "


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


class RecorderProcess:
    """The recorder process of one run, seen from the orchestrator (a :class:`RecordSink`).

    :meth:`write` never waits for the recorder: a thread of this object hands the records to
    the process's pipe, and up to ``queue_bytes`` of them wait in memory while the recorder
    lags behind (it runs at a lower CPU priority, :data:`RECORDER_NICE`). Only beyond that
    bound does :meth:`write` wait, once logged; nothing is dropped unless the process died.

    Args:
        path: the MCAP file to write.
        experiment: the experiment as run (after command-line overrides).
        log_time_ns: log time of ``/experiment`` [ns, wall clock, Unix epoch].
        chunk_size: MCAP chunk size [bytes].
        compression: MCAP chunk compression (``"zstd"``, ``"lz4"`` or ``"none"``).
        queue_bytes: records kept in memory while the pipe is full [bytes].
        python: interpreter to run the recorder with.
        live_port: serve the run live on this localhost port (0: a free one; ``None``: no
            live view), see :mod:`hilswarm.orchestrator.live_view`.

    Call :meth:`wait_ready` before the first tick and :meth:`close` on every exit path.
    """

    def __init__(
        self,
        path: str | Path,
        experiment: Experiment,
        *,
        log_time_ns: int,
        chunk_size: int = DEFAULT_CHUNK_SIZE,
        compression: str = DEFAULT_COMPRESSION,
        queue_bytes: int = DEFAULT_QUEUE_BYTES,
        python: str = sys.executable,
        live_port: int | None = None,
    ) -> None:
        if queue_bytes < 1:
            raise RecordingError(f"queue_bytes must be positive [bytes], got {queue_bytes}")
        self.path = Path(path)
        setup = pickle.dumps(
            {
                "path": str(self.path),
                "experiment": experiment,
                "log_time_ns": int(log_time_ns),
                "chunk_size": int(chunk_size),
                "compression": str(compression),
                "live_port": live_port,
            }
        )
        #: The live view's ``ws://`` URL once :meth:`wait_ready` returned ("" without one).
        self.live_url = ""
        self.process = subprocess.Popen(
            [python, "-m", "hilswarm.orchestrator.recorder_process"],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            start_new_session=True,
        )
        if self.process.stdin is None or self.process.stdout is None:  # pragma: no cover
            raise RecordingError("the recorder process has no pipes")
        self._fd = self.process.stdin.fileno()
        self.pipe_size = _enlarge_pipe(self._fd, PIPE_SIZE)
        self._failed = ""
        self._ready = False
        self._queue_bytes = queue_bytes
        self._queue: deque[bytes] = deque()
        self._queued = 0  # bytes in the queue and in the writer's hands
        self._closing = False
        self._waited = False  # write() waited for room once (logged once)
        self._changed = threading.Condition(threading.Lock())
        self.bytes_written = 0
        self.write_waits = 0
        self._writer = threading.Thread(
            target=self._hand_over, name=f"recorder pipe {self.path.name}", daemon=True
        )
        self._writer.start()
        self.write(_LENGTH.pack(len(setup)) + setup)

    def wait_ready(self, timeout_s: float = DEFAULT_READY_TIMEOUT_S) -> None:
        """Block until the file is created and the run's start is recorded.

        Raises:
            RecordingError: the process failed (e.g. the file cannot be created) or timed out.
        """
        if self._ready:
            return
        stdout = self.process.stdout
        if stdout is None:  # pragma: no cover
            raise RecordingError("the recorder process has no standard output")
        ready, _, _ = select.select([stdout], [], [], timeout_s)
        line = stdout.readline() if ready else b""
        if line.startswith(_READY_LIVE):
            self.live_url = line[len(_READY_LIVE) :].decode().strip()
            line = _READY
        if line != _READY:
            code = self.process.poll()
            if code is None and ready:  # its output closed: it is exiting
                with contextlib.suppress(subprocess.TimeoutExpired):
                    code = self.process.wait(timeout=10)
            why = f"exited with status {code}" if code is not None else "did not answer"
            raise RecordingError(
                f"the recorder process for {self.path} {why} within {timeout_s} s; "
                "see its log above"
            )
        self._ready = True

    def write(self, data: bytes) -> None:
        """Hand a batch of frames to the process; returns at once unless the queue is full.

        While ``queue_bytes`` of records wait for the pipe, this waits for room (logged once:
        the recorder cannot keep up); a batch larger than the bound waits for an empty queue.
        After the process died (:attr:`failed`) records are not kept.
        """
        if not data:
            return
        changed = self._changed
        with changed:
            if self._failed:
                return  # logged when it failed
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
                        return
                    changed.wait(1.0)
            if self._closing:
                logger.error(
                    "%d bytes of records for %s came after the recorder was closed: not recorded",
                    len(data),
                    self.path,
                )
                return
            self._queue.append(bytes(data))
            self._queued += len(data)
            changed.notify_all()

    def _hand_over(self) -> None:
        """The writer thread: move queued records into the pipe (blocking writes)."""
        changed = self._changed
        while True:
            with changed:
                while not self._queue and not self._closing:
                    changed.wait()
                if not self._queue:
                    return  # closing, and everything is handed over
                batch = self._queue.popleft() if len(self._queue) == 1 else b"".join(self._queue)
                self._queue.clear()
            try:
                view = memoryview(batch)
                while view:
                    written = os.write(self._fd, view)
                    view = view[written:]
            except OSError as exc:  # BrokenPipeError: the recorder died; the run goes on
                with changed:
                    lost = self._queued
                    self._failed = str(exc) or type(exc).__name__
                    self._queue.clear()
                    self._queued = 0
                    changed.notify_all()
                logger.error(
                    "the recorder process of %s stopped taking records (%s); %d bytes of "
                    "records not recorded",
                    self.path,
                    exc,
                    lost,
                )
                return
            with changed:
                self.bytes_written += len(batch)
                self._queued -= len(batch)
                changed.notify_all()

    @property
    def queued_bytes(self) -> int:
        """Records handed to :meth:`write` and not yet in the pipe [bytes]."""
        return self._queued

    @property
    def failed(self) -> str:
        """Why records could not be handed over ("" while all is well)."""
        return self._failed

    def close(self, timeout_s: float = DEFAULT_CLOSE_TIMEOUT_S) -> int | None:
        """End the stream; wait (bounded) for the file to be closed. Returns the exit status.

        The records still queued are handed over first. Idempotent. A process that does not
        finish in time is killed (the file is then recoverable with ``hilswarm recover``).
        """
        deadline = time.monotonic() + timeout_s
        with self._changed:
            self._closing = True
            self._changed.notify_all()
        self._writer.join(timeout=max(0.0, deadline - time.monotonic()))
        if self._writer.is_alive():  # the recorder stopped reading: it cannot finish in time
            logger.error(
                "the recorder process of %s did not take its last %d bytes of records; killing it",
                self.path,
                self._queued,
            )
            self.process.kill()
            self._writer.join(timeout=10)
        stdin = self.process.stdin
        if stdin is not None and not stdin.closed and not self._writer.is_alive():
            with contextlib.suppress(OSError):
                stdin.close()
        try:
            code = self.process.wait(timeout=max(0.0, deadline - time.monotonic()))
        except subprocess.TimeoutExpired:
            logger.error("the recorder process of %s did not finish; killing it", self.path)
            self.process.kill()
            code = self.process.wait(timeout=10)
        if self.process.stdout is not None:
            self.process.stdout.close()
        if code != 0:
            logger.error("the recorder process of %s exited with status %s", self.path, code)
        return code

    def __enter__(self) -> RecorderProcess:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()


def _read_exactly(fd: int, size: int) -> bytes:
    parts: list[bytes] = []
    while size:
        data = os.read(fd, size)
        if not data:
            raise RecordingError("the record stream ended before its set-up message")
        parts.append(data)
        size -= len(data)
    return b"".join(parts)


def record_stream(fd: int, ready: Any) -> int:
    """Record the stream on ``fd`` until it ends; returns the number of frames recorded.

    Args:
        fd: the read end of the manager's pipe.
        ready: a binary stream to which ``ready`` is written once recording has begun.
    """
    (size,) = _LENGTH.unpack(_read_exactly(fd, _LENGTH.size))
    setup = pickle.loads(_read_exactly(fd, size))  # our own parent process wrote it
    experiment: Experiment = setup["experiment"]
    log_time_ns: int = setup["log_time_ns"]
    live = None
    if setup.get("live_port") is not None:
        from hilswarm.orchestrator.live_view import LiveView  # noqa: PLC0415 - only with --live

        live = LiveView(int(setup["live_port"]), name=f"hilswarm {experiment.name}")
    with contextlib.ExitStack() as stack:
        if live is not None:
            stack.callback(live.close)
        recorder = stack.enter_context(
            Recorder(
                setup["path"],
                experiment,
                chunk_size=setup["chunk_size"],
                compression=setup.get("compression", DEFAULT_COMPRESSION),
                log_time_ns=log_time_ns,
                mirror=live,
            )
        )
        record_vehicles(recorder, experiment, log_time_ns=log_time_ns)
        ready.write(_READY if live is None else _READY_LIVE + live.url.encode() + b"\n")
        ready.flush()
        frames = FrameRecorder(recorder, experiment)
        reader = FrameReader()
        started = time.perf_counter()
        cpu_started = time.process_time()
        while True:
            data = os.read(fd, PIPE_SIZE)
            if not data:
                break
            frames.apply_all(reader.feed(data))
        if reader.pending:
            logger.error("record stream ended inside a frame (%d bytes lost)", reader.pending)
        logger.info(
            "recorded %d frames (%d bad, %d messages) in %.2f s (%.2f s CPU) to %s",
            frames.frames,
            frames.errors,
            recorder.message_count,
            time.perf_counter() - started,
            time.process_time() - cpu_started,
            setup["path"],
        )
    return frames.frames


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``python -m hilswarm.orchestrator.recorder_process``."""
    del argv
    logging.basicConfig(
        level=logging.WARNING, format="%(asctime)s %(levelname)s recorder %(name)s: %(message)s"
    )
    # Stopping is the orchestrator's job: it closes the pipe after the last record.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    # Not on the real-time path: let the agents and the manager have the CPU first.
    try:
        os.nice(RECORDER_NICE)
    except OSError as exc:
        logger.warning("could not lower the recorder's CPU priority: %s", exc)
    try:
        record_stream(sys.stdin.fileno(), sys.stdout.buffer)
    except (RecordingError, OSError, pickle.UnpicklingError, EOFError) as exc:
        logger.error("%s", exc)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
