"""The thread, pacing and lifecycle shared by the protocol-level mocap servers on loopback
(:mod:`.vrpn_sim`, :mod:`.natnet_sim`): one thread that answers what its sockets receive and
sends one frame per period, never a burst to catch up after a stall."""

from __future__ import annotations

import select
import socket
import threading
import time
from types import TracebackType
from typing import Self


class PacedServer:
    """A server thread that sends a frame every ``1 / rate_hz`` seconds (module docstring).

    Subclasses give the sockets to watch (:meth:`_readable`), what to do with those ready
    (:meth:`_on_readable`), one frame (:meth:`_send_frame`, which counts :attr:`frames`) and
    what to close at the end (:meth:`_close`).

    Args:
        rate_hz: frame rate [Hz] (> 0).
        name: the thread's name.
    """

    def __init__(self, rate_hz: float, name: str) -> None:
        if rate_hz <= 0.0:
            raise ValueError(f"rate_hz must be positive, got {rate_hz!r}")
        self.period_s = 1.0 / rate_hz
        self.frames = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._serve, name=name, daemon=True)

    def start(self) -> Self:
        """Serve on a thread of its own; returns self."""
        self._thread.start()
        return self

    def stop(self) -> None:
        """Stop serving and close the sockets (the clients see the server gone)."""
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(5.0)
        self._close()

    def __enter__(self) -> Self:
        return self.start()

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.stop()

    def _readable(self) -> list[socket.socket]:
        raise NotImplementedError

    def _on_readable(self, ready: list[socket.socket]) -> None:
        raise NotImplementedError

    def _send_frame(self) -> None:
        raise NotImplementedError

    def _close(self) -> None:
        raise NotImplementedError

    def _serve(self) -> None:
        next_frame = time.monotonic()
        while not self._stop.is_set():
            wait = max(0.0, next_frame - time.monotonic())
            ready, _, _ = select.select(self._readable(), [], [], wait)
            if ready:
                self._on_readable(ready)
            if time.monotonic() >= next_frame:
                self._send_frame()
                next_frame = max(next_frame + self.period_s, time.monotonic() - self.period_s)
