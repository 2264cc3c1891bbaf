"""Try to open a client session: ``python bus_probe.py ENDPOINT`` with user, password and CA
(PEM, may be empty) on stdin, one per line (the CA to the end). Prints ``open`` or ``refused``.

A stand-alone process so that it can run inside another network namespace.
"""

from __future__ import annotations

import sys

from hilswarm.agents import bus


def main() -> int:
    user, password, ca = [*sys.stdin.read().split("\n", 2), "", "", ""][:3]
    security = bus.SessionSecurity(user=user, password=password, ca_pem=ca or None)
    try:
        session = bus.open_session(bus.client_config([sys.argv[1]], security=security))
    except bus.BusConnectionError:
        print("refused")
        return 0
    session.close()
    print("open")
    return 0


if __name__ == "__main__":
    sys.exit(main())
