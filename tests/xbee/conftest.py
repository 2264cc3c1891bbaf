"""Fixtures of the XBee tests: a real Zenoh router on a free loopback port, client sessions."""

from __future__ import annotations

import socket
from collections.abc import Callable, Iterator

import pytest
import zenoh
from hilswarm.agents import bus


def _free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


@pytest.fixture
def client_session() -> Iterator[Callable[[], zenoh.Session]]:
    """Open client sessions (multicast scouting off) to a fresh router; all closed after."""
    endpoint = bus.loopback_endpoint(_free_port())
    router = bus.open_session(bus.listen_config([endpoint]))
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
