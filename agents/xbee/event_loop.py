"""A timed event loop on one thread: what the simulated air runs on.

Every simulated radio's state is touched only on this thread; other threads (pty readers,
robot UARTs, bus callbacks) hand their bytes over with :meth:`EventLoop.call_soon`. Events run
at their time on the monotonic clock [s], in time order (ties in submission order).
"""

from __future__ import annotations

import heapq
import itertools
import logging
import threading
import time
from collections.abc import Callable

_log = logging.getLogger(__name__)


class EventLoop:
    """Run callbacks at given monotonic times on one background thread.

    Args:
        name: thread name.
        clock: monotonic clock [s].
    """

    def __init__(self, name: str = "xbee-air", clock: Callable[[], float] = time.monotonic):
        self.clock = clock
        self.failures: list[BaseException] = []
        self._name = name
        self._heap: list[tuple[float, int, Callable[[], None]]] = []
        self._counter = itertools.count()
        self._cond = threading.Condition()
        self._stopping = False
        self._thread: threading.Thread | None = None

    def start(self) -> None:
        """Start the loop thread."""
        self._stopping = False
        self._thread = threading.Thread(target=self._run, name=self._name, daemon=True)
        self._thread.start()

    def call_at(self, when_s: float, fn: Callable[[], None]) -> None:
        """Run ``fn`` on the loop thread at ``when_s`` [s, monotonic clock]."""
        with self._cond:
            heapq.heappush(self._heap, (when_s, next(self._counter), fn))
            self._cond.notify()

    def call_soon(self, fn: Callable[[], None]) -> None:
        """Run ``fn`` on the loop thread as soon as possible."""
        self.call_at(self.clock(), fn)

    def stop(self) -> None:
        """Stop the thread (pending events are dropped). Idempotent."""
        with self._cond:
            self._stopping = True
            self._heap.clear()
            self._cond.notify()
        thread, self._thread = self._thread, None
        if thread is not None and thread is not threading.current_thread():
            thread.join(timeout=5.0)

    def _run(self) -> None:
        while True:
            with self._cond:
                while not self._stopping:
                    if self._heap:
                        wait = self._heap[0][0] - self.clock()
                        if wait <= 0:
                            break
                        self._cond.wait(wait)
                    else:
                        self._cond.wait(0.5)
                if self._stopping:
                    return
                _, _, fn = heapq.heappop(self._heap)
            try:
                fn()
            except Exception as exc:  # one bad event must not stop the air
                _log.exception("%s: event failed", self._name)
                self.failures.append(exc)
