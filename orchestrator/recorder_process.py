"""The recorder process: writes a run's MCAP file beside the instance manager, off its tick.

``hilswarm run`` starts ``python -m hilswarm.orchestrator.recorder_process`` with a pipe on
its standard input. The first message on the pipe says what to record (file, experiment as
loaded, log time of ``/experiment``); everything after it is the manager's record stream
(:mod:`hilswarm.orchestrator.record_stream`). The process writes ``/experiment``, each
vehicle's calibration and output names (:func:`~hilswarm.orchestrator.recorder.record_vehicles`),
says ``ready`` on its standard output, then records every frame. JSON encoding and MCAP
chunking happen here, on the other core, never under the manager's GIL.

End of the recording: the manager closes the pipe after its last frame; the process records
what is left and closes the file (summary, indexes, footer). The process runs in its own
session, so a Ctrl-C at the terminal reaches only the orchestrator, which then stops the run in
order and closes the pipe. If the orchestrator is killed, the pipe closes too and the file is
still closed properly; if the recorder itself is killed, ``hilswarm recover`` rewrites the file
from its complete chunks.
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
import time
from collections.abc import Sequence
from pathlib import Path
from types import TracebackType
from typing import Any

from hilswarm.agents.errors import RecordingError
from hilswarm.orchestrator.experiment import Experiment
from hilswarm.orchestrator.record_stream import FrameReader, FrameRecorder
from hilswarm.orchestrator.recorder import DEFAULT_CHUNK_SIZE, Recorder, record_vehicles

logger = logging.getLogger(__name__)

#: Pipe capacity asked for [bytes]: about a second of records of 64 agents at 200 Hz.
PIPE_SIZE = 1 << 20
#: Bound on waiting for the process to be ready (file created, vehicles described) [s].
DEFAULT_READY_TIMEOUT_S = 60.0
#: Bound on waiting for the process to finish the file after the pipe closed [s].
DEFAULT_CLOSE_TIMEOUT_S = 60.0

_LENGTH = struct.Struct("<I")
_F_SETPIPE_SZ = getattr(fcntl, "F_SETPIPE_SZ", 1031)
_READY = b"ready\n"


class RecorderProcess:
    """The recorder process of one run, seen from the orchestrator (a :class:`RecordSink`).

    Args:
        path: the MCAP file to write.
        experiment: the experiment as run (after command-line overrides).
        log_time_ns: log time of ``/experiment`` [ns, wall clock, Unix epoch].
        chunk_size: MCAP chunk size [bytes].
        python: interpreter to run the recorder with.

    Call :meth:`wait_ready` before the first tick and :meth:`close` on every exit path.
    """

    def __init__(
        self,
        path: str | Path,
        experiment: Experiment,
        *,
        log_time_ns: int,
        chunk_size: int = DEFAULT_CHUNK_SIZE,
        python: str = sys.executable,
    ) -> None:
        self.path = Path(path)
        self.process = subprocess.Popen(
            [python, "-m", "hilswarm.orchestrator.recorder_process"],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            start_new_session=True,
        )
        if self.process.stdin is None or self.process.stdout is None:  # pragma: no cover
            raise RecordingError("the recorder process has no pipes")
        self._fd = self.process.stdin.fileno()
        with contextlib.suppress(OSError):  # a smaller pipe only means earlier back-pressure
            fcntl.fcntl(self._fd, _F_SETPIPE_SZ, PIPE_SIZE)
        self._failed = ""
        self._ready = False
        self.bytes_written = 0
        setup = pickle.dumps(
            {
                "path": str(self.path),
                "experiment": experiment,
                "log_time_ns": int(log_time_ns),
                "chunk_size": int(chunk_size),
            }
        )
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
        """Hand a batch of frames to the process (blocks only while its pipe is full)."""
        if self._failed:
            return
        view = memoryview(data)
        try:
            while view:
                written = os.write(self._fd, view)
                view = view[written:]
        except OSError as exc:  # BrokenPipeError: the recorder died; the run goes on
            self._failed = str(exc)
            logger.error("the recorder process of %s stopped taking records: %s", self.path, exc)
            return
        self.bytes_written += len(data)

    @property
    def failed(self) -> str:
        """Why records could not be handed over ("" while all is well)."""
        return self._failed

    def close(self, timeout_s: float = DEFAULT_CLOSE_TIMEOUT_S) -> int | None:
        """End the stream; wait (bounded) for the file to be closed. Returns the exit status.

        Idempotent. A process that does not finish in time is killed (the file is then
        recoverable with ``hilswarm recover``).
        """
        stdin = self.process.stdin
        if stdin is not None and not stdin.closed:
            with contextlib.suppress(OSError):
                stdin.close()
        try:
            code = self.process.wait(timeout=timeout_s)
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
    with Recorder(
        setup["path"], experiment, chunk_size=setup["chunk_size"], log_time_ns=log_time_ns
    ) as recorder:
        record_vehicles(recorder, experiment, log_time_ns=log_time_ns)
        ready.write(_READY)
        ready.flush()
        frames = FrameRecorder(recorder, experiment)
        reader = FrameReader()
        started = time.perf_counter()
        while True:
            data = os.read(fd, PIPE_SIZE)
            if not data:
                break
            for kind, frame in reader.feed(data):
                frames.apply(kind, frame)
        if reader.pending:
            logger.error("record stream ended inside a frame (%d bytes lost)", reader.pending)
        logger.info(
            "recorded %d frames (%d bad) in %.2f s to %s",
            frames.frames,
            frames.errors,
            time.perf_counter() - started,
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
    try:
        record_stream(sys.stdin.fileno(), sys.stdout.buffer)
    except (RecordingError, OSError, pickle.UnpicklingError, EOFError) as exc:
        logger.error("%s", exc)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
