"""CPU time of a set of processes over a run, read by a small process of its own.

The benchmarks report each process's CPU per tick. Processes the runtime forks are reaped as
soon as they exit, so their CPU cannot be read after a run: it is read from
``/proc/<pid>/stat`` every ``period_s`` while the run lasts, and a process that exits counts
up to its last reading.

The readings are taken in a child process, not on a thread of the benchmark: the benchmark's
process is also the process measured (the orchestrator or the bare bus's router), and a
sampling thread there took the GIL beside the bus callbacks it was measuring and added its
own CPU to the manager's figure (14-20 µs per reading: ~5 ms per second at 34 processes). The
child keeps each ``stat`` file open and re-reads it with ``pread``.

    sampler = CpuSampler(pids).start()   # after the processes are up
    ...                                  # the run
    sampler.stop()                       # when its ticks are done
    sampler.total_s()                    # CPU of every process in between [s]
    sampler.machine_busy()               # how busy the machine's CPUs were in between [0, 1]

The child also reads the machine's own CPU times (``/proc/stat`` and ``/proc/uptime``,
``hilswarm.orchestrator.machine_cpu``) at its first and last reading:
:meth:`CpuSampler.machine_busy` is the fraction of all the machine's CPU time that was busy in
between, whoever's work it was (all but idle and I/O wait). Near 1, the run was bound by the
CPUs; a figure missed then is short of CPU, not waiting on something else.

``python benchmarks/cpu_sampler.py --short`` checks it on processes that burn a known amount
of CPU (measured against what they report, and what the sampling costs). Run with pids it is
that child (``--period S PID...``): it prints ``ready`` after the
first readings, reads every ``S`` seconds, and when its standard input closes prints one
JSON line ``{"first": [...], "last": [...], "own": S, "machine": [...]}`` (CPU [s] per pid,
in the order given, ``null`` for a process already gone at the start; its own CPU [s]; the
machine's busy and total CPU time [s] at the first and at the last reading) and exits.
"""

from __future__ import annotations

import argparse
import json
import os
import select
import subprocess
import sys
import time
from pathlib import Path

from hilswarm.orchestrator.machine_cpu import busy_fraction, parse_cpu_times

_CLOCK_TICKS = os.sysconf("SC_CLK_TCK")  # the unit of utime and stime [1/s]
_START_TIMEOUT_S = 30.0
_MAX_RUN_S = 6 * 3600.0  # the child gives up after this long, whatever its parent does


def cpu_from_stat(text: bytes) -> float:
    """User + system CPU [s] from the contents of a ``/proc/<pid>/stat`` file."""
    fields = text.rsplit(b")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / _CLOCK_TICKS


def process_cpu_s(pid: int) -> float | None:
    """User + system CPU of process ``pid`` so far [s]; ``None`` when it is gone."""
    try:
        return cpu_from_stat(Path(f"/proc/{pid}/stat").read_bytes())
    except OSError:
        return None


class CpuSampler:
    """CPU time of processes ``pids`` between :meth:`start` and :meth:`stop` (module doc).

    Raises:
        RuntimeError: the sampling process did not start or did not answer.
    """

    def __init__(self, pids: list[int], period_s: float = 0.1) -> None:
        self._pids = list(pids)
        self._period_s = period_s
        self._process: subprocess.Popen[str] | None = None
        self._first: list[float | None] = [None] * len(self._pids)
        self._last: list[float | None] = [None] * len(self._pids)
        self.own_cpu_s = float("nan")  #: the sampling process's own CPU [s], after stop()
        # the machine's busy and total CPU time [s] at the first and at the last reading
        self._machine: tuple[float, ...] = (0.0, 0.0, 0.0, 0.0)

    def start(self) -> CpuSampler:
        """Take the first readings, then keep sampling in the child (returns itself)."""
        self._process = subprocess.Popen(
            [sys.executable, __file__, "--period", repr(self._period_s),
             *map(str, self._pids)],
            stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True,
        )  # fmt: skip
        if _readline(self._process, _START_TIMEOUT_S) != "ready":
            self._process.kill()
            self._process.wait()
            raise RuntimeError("the CPU sampling process did not start")
        return self

    def stop(self) -> None:
        """Take a last reading and stop sampling (idempotent)."""
        process, self._process = self._process, None
        if process is None or process.stdin is None:
            return
        process.stdin.close()
        try:
            line = _readline(process, _START_TIMEOUT_S)
            readings = json.loads(line)
            self._first, self._last = readings["first"], readings["last"]
            self.own_cpu_s = float(readings["own"])
            self._machine = tuple(float(x) for x in readings["machine"])
        except (ValueError, KeyError, TypeError) as exc:
            raise RuntimeError(f"the CPU sampling process answered {line!r}") from exc
        finally:
            try:
                process.wait(5)
            except subprocess.TimeoutExpired:
                process.kill()
                process.wait()

    def total_s(self) -> float:
        """CPU of every process between start and stop [s]."""
        return sum(
            last - first
            for first, last in zip(self._first, self._last, strict=True)
            if first is not None and last is not None
        )

    def machine_busy(self) -> float:
        """The fraction [0, 1] of the machine's CPU time that was busy between the first and
        the last reading (anyone's work; NaN before :meth:`stop`)."""
        busy0, total0, busy1, total1 = self._machine
        return busy_fraction((busy0, total0), (busy1, total1))


def _readline(process: subprocess.Popen[str], timeout_s: float) -> str:
    """One line of the child's output within ``timeout_s`` ("" when none came)."""
    stdout = process.stdout
    if stdout is None:
        return ""
    ready, _, _ = select.select([stdout], [], [], timeout_s)
    return stdout.readline().strip() if ready else ""


def _sample(pids: list[int], period_s: float) -> None:
    """The child: read every ``period_s`` until standard input closes (module doc)."""
    files: list[int | None] = []
    for pid in pids:
        try:
            files.append(os.open(f"/proc/{pid}/stat", os.O_RDONLY))
        except OSError:
            files.append(None)

    def read(last: list[float | None]) -> None:
        for i, fd in enumerate(files):
            if fd is None:
                continue
            try:
                last[i] = cpu_from_stat(os.pread(fd, 4096, 0))
            except OSError:  # gone: it counts up to its last reading
                os.close(fd)
                files[i] = None

    stat = os.open("/proc/stat", os.O_RDONLY)
    uptime = os.open("/proc/uptime", os.O_RDONLY)

    def machine() -> tuple[float, float]:
        return parse_cpu_times(os.pread(stat, 1 << 18, 0), os.pread(uptime, 128, 0))

    first: list[float | None] = [None] * len(pids)
    machine_first = machine()
    read(first)
    last = list(first)
    print("ready", flush=True)
    stdin = sys.stdin.fileno()
    next_read = time.monotonic() + period_s
    give_up = time.monotonic() + _MAX_RUN_S
    while time.monotonic() < give_up:
        timeout = max(0.0, next_read - time.monotonic())
        ready, _, _ = select.select([stdin], [], [], timeout)
        if ready and not os.read(stdin, 4096):  # closed: the run's ticks are done
            break
        if time.monotonic() >= next_read:
            read(last)
            next_read += period_s
    read(last)
    machine_last = machine()
    os.close(stat)
    os.close(uptime)
    own = time.process_time()
    machine = [*machine_first, *machine_last]
    print(json.dumps({"first": first, "last": last, "own": own, "machine": machine}), flush=True)


def check(n: int, burn_s: float) -> str:
    """Sample ``n`` processes that each burn ``burn_s`` of CPU and exit one after another;
    the line compares what was measured with what they report themselves."""
    code = (
        "import sys, time\n"
        "end = time.process_time() + float(sys.argv[1])\n"
        "while time.process_time() < end: pass\n"
        "print(time.process_time())\n"
    )
    processes = [
        subprocess.Popen(
            [sys.executable, "-c", code, repr(burn_s * (i + 1) / n)],
            stdout=subprocess.PIPE,
            text=True,
        )
        for i in range(n)
    ]
    load = os.getloadavg()[0]
    sampler = CpuSampler([process.pid for process in processes]).start()
    started = time.monotonic()
    reported = sum(float(process.communicate(timeout=60)[0]) for process in processes)
    sampler.stop()
    elapsed = time.monotonic() - started
    sampling = sampler.own_cpu_s
    measured = sampler.total_s()
    return (
        f"cpu sampler: {n} processes, measured {measured:.2f} s of CPU against {reported:.2f} s "
        f"they report (ratio {measured / reported:.2f}; each exit loses at most one period and "
        f"the start-up before the first reading); the sampling process used "
        f"{1e3 * sampling:.0f} ms of CPU in {elapsed:.1f} s, its start-up included; the "
        f"machine's {os.cpu_count()} CPUs {100 * sampler.machine_busy():.0f} % busy meanwhile; "
        f"load {load:.2f} (1 min)"
    )


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--period", type=float, default=0.1, help="seconds between readings")
    parser.add_argument(
        "--short", action="store_true", help="check the sampler on processes of known CPU"
    )
    parser.add_argument("pids", type=int, nargs="*")
    args = parser.parse_args(argv)
    if not args.period > 0:
        parser.error(f"--period {args.period}: expected seconds > 0")
    if args.short:
        print(check(4, 2.0))
        return 0
    _sample(args.pids, args.period)
    return 0


if __name__ == "__main__":
    sys.exit(main())
