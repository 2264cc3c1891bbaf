"""``simavr://`` — the real hilswarm firmware running in the AVR simulator.

``board_for_url("simavr://uno")`` starts ``firmware/build/hilswarm-simavr`` (see
``firmware/simavr/README.md``) on the firmware ELF ``firmware/build/<board>/hilswarm.elf`` in its
own process group, reads the pseudo-terminal it bridges the simulated UART to, and speaks the wire
protocol through a :class:`~.serial_board.SerialBoard` on it: every byte goes through the same
code path as a USB-connected Arduino. Any experiment runs on the simulated firmware by setting
``link = "simavr://uno"``.

URL: ``simavr://[uno|duemilanove|fio][?paced=1&board_id=N]``. ``paced=1`` makes simulated time
follow the wall clock (real UART timing at 115200 baud: timing tests, benchmarks); the default
runs unpaced (several times faster than real time: functional tests).

Closing the loop: with ``plant=`` (a ``PinPlant``) each :meth:`SimavrBoard.exchange` is
lockstep, in the same order as ``sim://``: a TICK carrying the writes; the harness ``state``
gives the pins' outputs as the firmware drives them (digital levels, PWM duty, servo µs);
``plant.advance(outputs, dt)``; the returned voltages are injected (``adc`` for analog inputs,
``din`` for digital ones); then a TICK carrying the reads samples them. ``dt`` is the fixed step
given (like ``sim://``) or, without one, the simulated time that elapsed.

The firmware folder is found next to the package source (``<repo>/firmware``) or at
``$HILSWARM_FIRMWARE_DIR``. Not built yet? ``make -C firmware``.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import select
import signal
import subprocess
import tempfile
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Any, Protocol
from urllib.parse import parse_qsl, urlsplit

from hilswarm.agents.errors import BoardConnectionError, LinkUrlError, SimulatorError
from hilswarm.agents.link.board import (
    PIN_COUNT,
    Board,
    BoardInfo,
    BoardStatus,
    PinConfig,
    PinMode,
    TickReply,
)
from hilswarm.agents.link.serial_board import LinkEvent, SerialBoard

_log = logging.getLogger(__name__)

#: Environment variable overriding the firmware folder.
FIRMWARE_DIR_ENV = "HILSWARM_FIRMWARE_DIR"
#: Harness executable, relative to the firmware folder.
HARNESS_RELPATH = Path("build") / "hilswarm-simavr"
#: Seconds allowed for the harness to print its ``PTY`` line.
_START_TIMEOUT_S = 10.0
#: Seconds allowed for one control-channel reply.
_COMMAND_TIMEOUT_S = 5.0
#: Shortest control-command timeout a board gives its harness [s].
_MIN_COMMAND_TIMEOUT_S = 1.0
#: Seconds given to each stop stage (quit, SIGTERM) before the next.
_STOP_STAGE_S = 2.0


class PinPlant(Protocol):
    """What closes the loop: pin outputs (wire units) held for ``dt`` [s] -> input volts [V]."""

    def advance(self, outputs: Mapping[int, int], dt: float) -> Mapping[int, float]:
        """Advance by ``dt`` [s] with ``outputs`` held; return input voltages [V] by pin."""
        ...


@dataclass(frozen=True, slots=True)
class SimavrProfile:
    """How a board profile is simulated.

    Attributes:
        build: firmware build folder under ``firmware/build``.
        freq_hz: CPU clock [Hz].
        vcc_mv: supply and analog reference [mV].
    """

    build: str
    freq_hz: int
    vcc_mv: int


#: Board profiles the simulator runs.
SIMAVR_PROFILES: dict[str, SimavrProfile] = {
    "uno": SimavrProfile("uno", 16_000_000, 5000),
    "duemilanove": SimavrProfile("uno", 16_000_000, 5000),
    "fio": SimavrProfile("fio", 8_000_000, 3300),
}


def firmware_dir() -> Path:
    """The firmware folder: ``$HILSWARM_FIRMWARE_DIR`` or ``<repo>/firmware`` beside the source."""
    override = os.environ.get(FIRMWARE_DIR_ENV)
    if override:
        return Path(override).expanduser().resolve()
    return Path(__file__).resolve().parents[2] / "firmware"


def locate_build(profile: str = "uno") -> tuple[Path, Path]:
    """Return ``(harness, elf)`` for ``profile``.

    Raises:
        SimulatorError: unknown profile, or the harness/ELF is not built (names the missing
            file and the command that builds it).
    """
    if profile not in SIMAVR_PROFILES:
        raise SimulatorError(
            f"simavr: unknown board profile {profile!r}; known: "
            f"{', '.join(sorted(SIMAVR_PROFILES))}"
        )
    root = firmware_dir()
    harness = root / HARNESS_RELPATH
    elf = root / "build" / SIMAVR_PROFILES[profile].build / "hilswarm.elf"
    target = "" if SIMAVR_PROFILES[profile].build == "uno" else f" {SIMAVR_PROFILES[profile].build}"
    for path in (harness, elf):
        if not path.is_file():
            raise SimulatorError(
                f"simavr: {path} is not built; run `make -C {root} all{target}` (needs gcc-avr, "
                f"avr-libc, arduino-core-avr and libsimavr-dev; set ${FIRMWARE_DIR_ENV} to use "
                "another firmware folder)"
            )
    return harness, elf


class SimavrHarness:
    """One running ``hilswarm-simavr`` process and its line-based control channel.

    Args:
        profile: board profile (``uno``, ``duemilanove``, ``fio``).
        paced: simulated time follows the wall clock.
    """

    def __init__(self, profile: str = "uno", *, paced: bool = False) -> None:
        self.profile = profile
        self.paced = paced
        self.harness_path, self.elf_path = locate_build(profile)
        self.process: subprocess.Popen[bytes] | None = None
        self.pty_path = ""
        self._stdout_buffer = bytearray()
        #: How long one control command may take [s]; past it the harness counts as stalled.
        self.command_timeout_s = _COMMAND_TIMEOUT_S
        self._unanswered = 0  # commands whose reply did not come in time (it comes later)
        self._stderr_file: IO[bytes] | None = None

    def start(self) -> str:
        """Start the process (own process group); return the pty path it bridges the UART to."""
        self._stdout_buffer = bytearray()
        self._unanswered = 0
        sim = SIMAVR_PROFILES[self.profile]
        command = [
            str(self.harness_path),
            "--elf",
            str(self.elf_path),
            "--freq",
            str(sim.freq_hz),
            "--vcc-mv",
            str(sim.vcc_mv),
            "--paced" if self.paced else "--unpaced",
        ]
        self._stderr_file = tempfile.TemporaryFile()  # noqa: SIM115 - closed in stop()
        try:
            self.process = subprocess.Popen(
                command,
                stdin=subprocess.PIPE,
                stdout=subprocess.PIPE,
                stderr=self._stderr_file,
                start_new_session=True,
            )
        except OSError as exc:
            raise SimulatorError(f"simavr: cannot start {command[0]}: {exc}") from exc
        try:
            line = self._read_line(_START_TIMEOUT_S)
        except SimulatorError:
            self.stop()
            raise
        if not line.startswith("PTY "):
            self.stop()
            raise SimulatorError(f"simavr: harness printed {line!r}, expected 'PTY <path>'")
        self.pty_path = line[4:].strip()
        _log.info(
            "simavr harness pid %d runs %s on %s (%s)",
            self.process.pid,
            self.elf_path,
            self.pty_path,
            "paced" if self.paced else "unpaced",
        )
        return self.pty_path

    def stderr_tail(self, limit: int = 2000) -> str:
        """The last ``limit`` characters the harness wrote on stderr."""
        if self._stderr_file is None:
            return ""
        with contextlib.suppress(OSError, ValueError):
            self._stderr_file.seek(0)
            return self._stderr_file.read().decode(errors="replace")[-limit:]
        return ""

    def _read_line(self, timeout_s: float) -> str:
        process = self.process
        if process is None or process.stdout is None:
            raise SimulatorError("simavr: harness is not running")
        fd = process.stdout.fileno()
        deadline = time.monotonic() + timeout_s
        while b"\n" not in self._stdout_buffer:
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                raise SimulatorError(
                    f"simavr: no answer from the harness within {timeout_s} s; "
                    f"stderr: {self.stderr_tail()}"
                )
            ready, _, _ = select.select([fd], [], [], remaining)
            if not ready:
                continue
            chunk = os.read(fd, 4096)
            if not chunk:
                code = process.poll()
                raise SimulatorError(
                    f"simavr: harness exited (status {code}); stderr: {self.stderr_tail()}"
                )
            self._stdout_buffer += chunk
        line, _, rest = bytes(self._stdout_buffer).partition(b"\n")
        self._stdout_buffer = bytearray(rest)
        return line.decode(errors="replace").rstrip("\r")

    def command(self, line: str) -> str:
        """Send one control command; return its reply line (raises on ``err ...``).

        A harness that does not answer within :attr:`command_timeout_s` (stopped, stalled)
        raises :class:`SimulatorError`; the reply it owes is read and dropped before the next
        command's, so replies never go to the wrong command.
        """
        process = self.process
        if process is None or process.stdin is None or process.poll() is not None:
            raise SimulatorError(
                f"simavr: harness is not running (command {line!r}); stderr: {self.stderr_tail()}"
            )
        while self._unanswered:  # late replies of commands that timed out
            self._read_line(self.command_timeout_s)
            self._unanswered -= 1
        try:
            process.stdin.write(line.encode() + b"\n")
            process.stdin.flush()
        except OSError as exc:
            raise SimulatorError(f"simavr: harness control channel closed: {exc}") from exc
        try:
            reply = self._read_line(self.command_timeout_s)
        except SimulatorError:
            self._unanswered += 1
            raise
        if reply.startswith("err"):
            raise SimulatorError(f"simavr: harness refused {line!r}: {reply}")
        return reply

    def state(self) -> dict[str, Any]:
        """The harness ``state`` snapshot (``t_us``, ``digital``, ``pwm``, ``servo``)."""
        reply = self.command("state")
        try:
            state: dict[str, Any] = json.loads(reply)
        except json.JSONDecodeError as exc:
            raise SimulatorError(f"simavr: 'state' reply is not JSON: {reply!r}") from exc
        return state

    def stop(self) -> None:
        """Stop the harness: ``quit``, then SIGTERM, then SIGKILL to its process group."""
        process, self.process = self.process, None
        if process is not None:
            self._terminate(process)
        if self._stderr_file is not None:
            self._stderr_file.close()
            self._stderr_file = None

    @staticmethod
    def _terminate(process: subprocess.Popen[bytes]) -> None:
        if process.poll() is None and process.stdin is not None:
            with contextlib.suppress(OSError, ValueError):
                process.stdin.write(b"quit\n")
                process.stdin.flush()
        stages: list[Callable[[], None]] = [
            lambda: None,
            lambda: os.killpg(process.pid, signal.SIGTERM),
            lambda: os.killpg(process.pid, signal.SIGKILL),
        ]
        for stage in stages:
            if process.poll() is not None:
                break
            with contextlib.suppress(ProcessLookupError, PermissionError):
                stage()
            with contextlib.suppress(subprocess.TimeoutExpired):
                process.wait(timeout=_STOP_STAGE_S)
        for stream in (process.stdin, process.stdout):
            if stream is not None:
                with contextlib.suppress(OSError):
                    stream.close()
        if process.poll() is None:
            _log.error("simavr harness pid %d did not stop", process.pid)


def outputs_from_state(state: Mapping[str, Any], modes: Mapping[int, PinMode]) -> dict[int, int]:
    """Wire value of every configured output pin in a harness ``state`` snapshot.

    DIGITAL_OUT: the level (0/1). PWM: the duty 0-255 (a pin at duty 0 or 255 is driven as a
    plain digital pin by the Arduino core, so its level gives 0 or 255). SERVO: pulse width [µs]
    (0 while no pulse is generated).
    """
    digital: Sequence[int] = state["digital"]
    pwm: Mapping[str, int] = state.get("pwm", {})
    servo: Mapping[str, int] = state.get("servo", {})
    outputs: dict[int, int] = {}
    for pin, mode in modes.items():
        level = digital[pin] if pin < len(digital) else -1
        if mode == PinMode.DIGITAL_OUT:
            outputs[pin] = max(level, 0)
        elif mode == PinMode.PWM:
            outputs[pin] = int(pwm[str(pin)]) if str(pin) in pwm else max(level, 0) * 255
        elif mode == PinMode.SERVO:
            outputs[pin] = int(servo.get(str(pin), 0))
    return outputs


class SimavrBoard(Board):
    """The real firmware in simavr, reached through a :class:`SerialBoard` on the harness pty.

    Args:
        profile: ``uno``, ``duemilanove`` or ``fio``.
        plant: optional ``PinPlant`` closing the loop (see the module docstring).
        dt: fixed plant step per exchange [s]; ``None`` uses the elapsed simulated time.
        paced: simulated time follows the wall clock.
        url: URL reported in messages.
        serial_options: passed to :class:`SerialBoard` (``board_id``, ``timeout_s``,
            ``retries``, ``on_event``...); ``reconnect_timeout_s`` bounds :meth:`reconnect`
            instead (the serial link never re-opens the pty by itself).
    """

    def __init__(
        self,
        profile: str = "uno",
        *,
        plant: PinPlant | None = None,
        dt: float | None = None,
        paced: bool = False,
        url: str = "simavr://uno",
        **serial_options: Any,
    ) -> None:
        if dt is not None and not dt > 0:
            raise LinkUrlError(f"{url!r}: dt must be > 0 [s], got {dt!r}")
        if plant is not None and not callable(getattr(plant, "advance", None)):
            raise LinkUrlError(f"{url!r}: plant {plant!r} has no advance(outputs, dt)")
        self.url = url
        self.profile = profile
        self.plant = plant
        self.dt = dt
        self.paced = paced
        self.harness = SimavrHarness(profile, paced=paced)  # raises if not built
        # The serial link never re-opens the pty by itself: a lost pty means a dead harness,
        # and its path may be handed to another process's pseudo-terminal at once. Its
        # reconnect_timeout_s is how long reconnect() (the agent) may keep trying instead.
        self._link_timeout_s = float(serial_options.pop("reconnect_timeout_s", 5.0))
        self._serial_options = {**serial_options, "reconnect_timeout_s": 0.0}
        # A plant step's control command is part of the exchange: a harness that does not
        # answer it within one serial request's time is a stalled board too.
        self.harness.command_timeout_s = max(
            _MIN_COMMAND_TIMEOUT_S,
            float(serial_options.get("timeout_s", 0.25))
            * (int(serial_options.get("retries", 3)) + 1),
        )
        self.serial: SerialBoard | None = None
        self._modes: dict[int, PinMode] = {}
        self._last_t_us: int | None = None
        self._volts: dict[int, float] = {}
        self._link_listeners: list[Callable[[str, str], None]] = []

    @property
    def events(self) -> list[LinkEvent]:
        """Link events of the serial link (empty before :meth:`open`)."""
        return self.serial.events if self.serial is not None else []

    def _require_serial(self) -> SerialBoard:
        if self.serial is None:
            raise BoardConnectionError(f"{self.url}: not open: call open() first")
        return self.serial

    def open(self) -> BoardInfo:
        """Start the harness and perform the HELLO handshake over its pty."""
        if self.serial is None:
            pty = self.harness.start()
            self.serial = SerialBoard(pty, **self._serial_options)
            for listener in self._link_listeners:
                self.serial.add_link_listener(listener)
        try:
            return self.serial.open()
        except BaseException:
            self.close()
            raise

    @property
    def info(self) -> BoardInfo:
        """The last HELLO result."""
        return self._require_serial().info

    def configure(self, pins: Sequence[PinConfig], *, watchdog_s: float) -> None:
        """CONFIG over the wire; remember the modes to read outputs and inject inputs."""
        pins = tuple(pins)
        self._require_serial().configure(pins, watchdog_s=watchdog_s)
        self._modes = {p.pin: PinMode(p.mode) for p in pins}

    def exchange(self, writes: Mapping[int, int], reads: Sequence[int]) -> TickReply:
        """One tick; with a plant: writes, plant step, inputs injected, then the samples."""
        serial = self._require_serial()
        if self.plant is None:
            return serial.exchange(writes, reads)
        first = serial.exchange(writes, [])
        self._step_plant()
        second = serial.exchange({}, reads)
        return TickReply(
            second.seq,
            BoardStatus(first.status | second.status),
            second.board_time_s,
            second.samples,
        )

    def _step_plant(self) -> None:
        if self.plant is None:
            return
        state = self.harness.state()
        t_us = int(state["t_us"])
        if self.dt is not None:
            dt = self.dt
        else:
            dt = 0.0 if self._last_t_us is None else (t_us - self._last_t_us) / 1e6
        self._last_t_us = t_us
        volts = self.plant.advance(outputs_from_state(state, self._modes), dt)
        for pin, value in volts.items():
            self.set_input_voltage(int(pin), float(value))

    def set_input_voltage(self, pin: int, volts: float) -> None:
        """Put ``volts`` [V] on input ``pin``: ``adc`` for analog pins (14-19), else ``din``."""
        if not 0 <= pin < PIN_COUNT:
            raise SimulatorError(f"simavr: no pin {pin} to put {volts} V on")
        if self._volts.get(pin) == volts:
            return  # unchanged: spare a control round trip
        vcc_v = SIMAVR_PROFILES[self.profile].vcc_mv / 1000.0
        if self._modes.get(pin) == PinMode.ANALOG_IN or (pin >= 14 and pin not in self._modes):
            millivolts = min(max(round(volts * 1000.0), 0), 0xFFFF)
            self.harness.command(f"adc {pin} {millivolts}")
        else:
            self.harness.command(f"din {pin} {1 if volts >= vcc_v / 2 else 0}")
        self._volts[pin] = volts

    def set_analog_input(self, pin: int, volts: float) -> None:
        """Put ``volts`` [V] on analog pin ``pin`` (14-19 = A0-A5)."""
        millivolts = min(max(round(volts * 1000.0), 0), 0xFFFF)
        self.harness.command(f"adc {pin} {millivolts}")
        self._volts[pin] = volts

    def set_digital_input(self, pin: int, level: int) -> None:
        """Drive digital input ``pin`` externally low (0) or high (1)."""
        self.harness.command(f"din {pin} {int(bool(level))}")

    def read_outputs(self) -> dict[int, int]:
        """Wire value of every configured output as the firmware drives it (from the pins)."""
        return self.read_outputs_from(self.harness.state())

    def read_outputs_from(self, state: Mapping[str, Any]) -> dict[int, int]:
        """Like :meth:`read_outputs`, from a ``state`` snapshot taken already."""
        return outputs_from_state(state, self._modes)

    def estop(self) -> TickReply:
        """ESTOP over the wire."""
        return self._require_serial().estop()

    def set_board_id(self, board_id: int) -> int:
        """SET_ID over the wire; returns the id read back from EEPROM."""
        return self._require_serial().set_board_id(board_id)

    @property
    def link_timeout_s(self) -> float:  # type: ignore[override]
        """How long a lost link may be re-tried by :meth:`reconnect` [s] (the
        ``reconnect_timeout_s`` option, default 5 s)."""
        return self._link_timeout_s

    def request_estop(self) -> bool:
        """ESTOP on the serial link's own path (see :meth:`SerialBoard.request_estop`)."""
        serial = self.serial
        return serial.request_estop() if serial is not None else False

    def add_link_listener(self, listener: Callable[[str, str], None]) -> None:
        """Link events of the serial link (see :meth:`SerialBoard.add_link_listener`)."""
        self._link_listeners.append(listener)
        if self.serial is not None:
            self.serial.add_link_listener(listener)

    def abort(self) -> None:
        """Make a blocked request give up (see :meth:`SerialBoard.abort`)."""
        serial = self.serial
        if serial is not None:
            serial.abort()

    def reconnect(self) -> BoardInfo:
        """One attempt to re-establish the link; a harness that died is started again first.

        A new harness is a new board (it boots, a new pty): the serial link re-opens on it,
        handshakes and re-applies the configuration, and the input voltages injected before
        are put on its pins again (what is wired to the board stays wired).
        """
        serial = self._require_serial()
        process = self.harness.process
        if process is None or process.poll() is not None:
            self.harness.stop()
            serial.port_url = self.harness.start()
            self._last_t_us = None
            volts, self._volts = self._volts, {}
            for pin, value in volts.items():
                self.set_input_voltage(pin, value)
        return serial.reconnect()

    def close(self) -> None:
        """Close the link and stop the harness (quit, SIGTERM, SIGKILL). Idempotent."""
        serial, self.serial = self.serial, None
        if serial is not None:
            serial.close()
        self.harness.stop()

    def __repr__(self) -> str:
        return f"SimavrBoard({self.profile!r}, paced={self.paced}, url={self.url!r})"


def parse_url(url: str) -> tuple[str, dict[str, Any]]:
    """Parse ``simavr://[uno|duemilanove|fio][?paced=1&board_id=N]`` into ``(profile, options)``.

    Raises:
        LinkUrlError: wrong scheme, unknown profile or option, bad value.
    """
    parts = urlsplit(url)
    if parts.scheme.lower() != "simavr":
        raise LinkUrlError(f"{url!r} is not a simavr:// URL")
    profile = (parts.netloc or parts.path.strip("/") or "uno").lower()
    if profile not in SIMAVR_PROFILES:
        raise LinkUrlError(
            f"{url!r}: unknown board profile {profile!r}; known: "
            f"{', '.join(sorted(SIMAVR_PROFILES))}"
        )
    options: dict[str, Any] = {}
    for key, value in parse_qsl(parts.query, keep_blank_values=True):
        if key == "paced":
            if value not in ("0", "1", "true", "false"):
                raise LinkUrlError(f"{url!r}: paced must be 0 or 1, got {value!r}")
            options["paced"] = value in ("1", "true")
        elif key == "board_id":
            if not value.isdigit() or int(value) > 0xFFFF:
                raise LinkUrlError(f"{url!r}: board_id must be an integer 0-65535, got {value!r}")
            options["board_id"] = int(value)
        else:
            raise LinkUrlError(f"{url!r}: unknown option {key!r} (known: paced, board_id)")
    return profile, options


def validate_url(url: str, *, local: bool = True) -> None:
    """Check ``url`` as :func:`board_from_url` would, and (``local``: the board runs on this
    machine) that its firmware is built.

    Raises:
        LinkUrlError: a bad URL, or the firmware/harness of its profile is not built.
    """
    profile, _ = parse_url(url)
    if not local:
        return
    try:
        locate_build(profile)
    except SimulatorError as exc:
        raise LinkUrlError(f"{url!r}: {exc}") from None


def board_from_url(url: str, **options: Any) -> SimavrBoard:
    """Build a :class:`SimavrBoard` from ``simavr://[uno|duemilanove|fio][?paced=1&board_id=N]``.

    ``options`` go to :class:`SimavrBoard` (``plant=``, ``dt=``, serial options).

    Raises:
        LinkUrlError: wrong scheme, unknown profile or option, bad value.
        SimulatorError: the firmware or harness is not built.
    """
    profile, from_url = parse_url(url)
    clash = sorted(set(from_url) & set(options))
    if clash:
        raise LinkUrlError(f"{url!r}: {', '.join(clash)} given both in the URL and as an option")
    return SimavrBoard(profile, url=url, **from_url, **options)
