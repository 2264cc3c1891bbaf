"""Zenoh's receiving thread keeps its Python thread state under ``bus_callback.callback``.

Seen from Python: a ``threading.local`` value set in one callback is still there in the next
callback on the same thread only when the thread state lived on between them. Without the
wrapper PyO3 deletes the state after every callback (the probe's first half shows it, so this
test would notice if the wrapper stopped mattering or stopped working).
"""

from __future__ import annotations

import json
import subprocess
import sys

#: A router and a client of it (bus.open_session: the lean runtime, scouting off); the client
#: puts N messages to a subscriber of the router's, first a plain ``indirect=False`` callback,
#: then one wrapped by bus_callback.callback. Prints, per half, what the callbacks saw.
_PROBE = """
import json, threading
import zenoh
from hilswarm.agents import bus, bus_callback

N = 20
router = bus.open_session(bus.listen_config([bus.loopback_endpoint(0)]))
client = bus.open_session(bus.client_config(bus.bound_endpoints(router)))

def half(key, wrap):
    local = threading.local()
    seen = []
    answered = threading.Semaphore(0)

    def on_sample(sample):
        seen.append([threading.get_ident(), getattr(local, "mark", None)])
        local.mark = int(sample.payload.to_bytes())
        answered.release()

    handler = bus_callback.callback(on_sample) if wrap else zenoh.handlers.Callback(
        on_sample, indirect=False
    )
    subscriber = router.declare_subscriber(key, handler)
    publisher = client.declare_publisher(key)
    for i in range(N):  # one at a time: each callback has returned before the next put
        publisher.put(str(i).encode())
        if not answered.acquire(timeout=10):
            raise SystemExit(f"no callback for message {i} within 10 s")
    publisher.undeclare()
    subscriber.undeclare()
    return seen

plain = half("probe/plain", False)
kept = half("probe/kept", True)
print(json.dumps({"plain": plain, "kept": kept, "main": threading.get_ident()}))
client.close()
router.close()
"""


def _probe() -> dict[str, list[list[int | None]] | int]:
    result = subprocess.run(
        [sys.executable, "-c", _PROBE], check=False, capture_output=True, text=True, timeout=60
    )
    assert result.returncode == 0, result.stderr
    return json.loads(result.stdout.strip().splitlines()[-1])


def _marks_after_a_callback_on_the_same_thread(
    calls: list[list[int | None]],
) -> list[tuple[int, int | None]]:
    """(index, what the callback saw) for each callback run right after one on its thread."""
    return [(i, calls[i][1]) for i in range(1, len(calls)) if calls[i][0] == calls[i - 1][0]]


def test_the_receiving_thread_keeps_its_thread_state_only_with_the_wrapper() -> None:
    seen = _probe()
    plain, kept, main = seen["plain"], seen["kept"], seen["main"]
    assert len(plain) == len(kept) == 20
    for calls in (plain, kept):  # on Zenoh's own thread, not a Python one
        assert all(ident != main for ident, _ in calls)
    # Plain: a new thread state per callback, so the previous callback's mark is gone.
    followers = _marks_after_a_callback_on_the_same_thread(plain)
    assert len(followers) >= 10, plain  # the lean runtime receives on one thread
    assert all(mark is None for _, mark in followers), plain
    # Wrapped: the state lives on, with the mark the previous callback left.
    followers = _marks_after_a_callback_on_the_same_thread(kept)
    assert len(followers) >= 10, kept
    assert all(mark == i - 1 for i, mark in followers), kept
