"""Fixtures of the XBee tests: a real Zenoh router on a free loopback port, client sessions."""

from __future__ import annotations

from collections.abc import Callable, Iterator

import pytest
import zenoh
from hilswarm.agents import bus


@pytest.fixture
def client_session() -> Iterator[Callable[[], zenoh.Session]]:
    """Open client sessions (multicast scouting off) to a fresh router; all closed after."""
    router = bus.open_session(bus.listen_config([bus.loopback_endpoint(0)]))
    (endpoint,) = bus.bound_endpoints(router)  # the free port the router bound
    sessions: list[zenoh.Session] = []

    def open_client() -> zenoh.Session:
        session = bus.open_session(bus.client_config([endpoint]))
        sessions.append(session)
        return session

    try:
        yield open_client
    finally:
        for session in sessions:
            session.close()
        router.close()
