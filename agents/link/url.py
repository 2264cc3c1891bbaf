"""Pick a board transport by URL, the way pyserial's ``serial_for_url`` does.

Schemes are registered by the transport modules; :func:`open_board` imports them lazily so that
a user of ``sim://`` never needs pyserial or the AVR simulator.

Known schemes:

* ``sim://[profile][?options]`` — in-process simulated board (:mod:`.sim_board`).
* ``simavr://[profile][?options]`` — the real firmware in the AVR simulator (:mod:`.simavr`).
* ``xbee://<64-bit address>`` — a board behind the XBee API-mode gateway, reached over the bus
  (:mod:`hilswarm.agents.xbee.transport`; needs ``session=``, ``experiment=``, ``agent=``).
* anything else pyserial understands — a serial port running the hilswarm firmware
  (``/dev/ttyUSB0``, ``COM5``, ``loop://``, ``socket://host:port``, ``rfc2217://host:port``).
"""

from __future__ import annotations

import importlib
from collections.abc import Callable
from typing import Any
from urllib.parse import parse_qsl, urlsplit

from hilswarm.agents.errors import LinkUrlError
from hilswarm.agents.link.board import Board

BoardFactory = Callable[..., Board]

#: scheme -> "module:function" building a Board from (url, **options).
_SCHEMES: dict[str, str] = {
    "sim": "hilswarm.agents.link.sim_board:board_from_url",
    "simavr": "hilswarm.agents.link.simavr:board_from_url",
    "xbee": "hilswarm.agents.xbee.transport:board_from_url",
}
#: pyserial URL schemes (and bare device paths) go to the serial transport.
_SERIAL_FACTORY = "hilswarm.agents.link.serial_board:board_from_url"
#: kind -> "module:function" checking a URL of that kind completely without opening anything.
_VALIDATORS: dict[str, str] = {
    "sim": "hilswarm.agents.link.sim_board:validate_url",
    "simavr": "hilswarm.agents.link.simavr:validate_url",
    "serial": "hilswarm.agents.link.serial_board:validate_url",
    "xbee": "hilswarm.agents.xbee.config:validate_url",
}
_PYSERIAL_SCHEMES = {"loop", "socket", "rfc2217", "spy", "alt", "hwgrep", "cp2110"}


def link_scheme(url: str) -> str:
    """Return the transport kind of ``url``: ``sim``, ``simavr``, ``xbee`` or ``serial``.

    Raises:
        LinkUrlError: if the URL is empty or names a scheme no transport handles.
    """
    if not isinstance(url, str) or not url.strip():
        raise LinkUrlError(f"link URL must be a non-empty string, got {url!r}")
    if "://" not in url:
        # A bare device path: /dev/ttyUSB0, COM5.
        if url.startswith("/dev/") or url.upper().startswith("COM"):
            return "serial"
        raise LinkUrlError(
            f"link URL {url!r} has no scheme; expected sim://, simavr://, "
            "a serial device such as /dev/ttyUSB0, or a pyserial URL (loop://, socket://...)"
        )
    scheme = urlsplit(url).scheme.lower()
    if scheme in _SCHEMES:
        return scheme
    if scheme in _PYSERIAL_SCHEMES:
        return "serial"
    known = ", ".join(sorted([*_SCHEMES, *_PYSERIAL_SCHEMES]))
    raise LinkUrlError(f"link URL {url!r}: unknown scheme {scheme!r}; known schemes: {known}")


def is_simulated(url: str) -> bool:
    """True when ``url``'s board is simulated with the vehicle's simulated hardware as plant:
    ``sim://``, ``simavr://``, or ``xbee://...?sim=...`` (a simulated robot behind a simulated
    radio). Raises :class:`LinkUrlError` like :func:`link_scheme`."""
    kind = link_scheme(url)
    if kind == "xbee":
        return "sim" in dict(parse_qsl(urlsplit(url).query))
    return kind in ("sim", "simavr")


def validate_link_url(url: str, *, local: bool = True) -> str:
    """Check ``url`` as far as possible without opening it; return its kind (:func:`link_scheme`).

    Beyond the scheme: the board profile and query options (``sim://mega`` is refused), a
    serial device path exists, ``socket://`` / ``rfc2217://`` have ``HOST:PORT``, the firmware of
    a ``simavr://`` profile is built. The transports use the same parsers when they open.
    ``local=False`` (the board is on another machine, e.g. ``hilswarm run --remote``) skips
    what only that machine can know: the device and the firmware build.

    Raises:
        LinkUrlError: what is wrong with ``url``.
    """
    kind = link_scheme(url)
    validator = _VALIDATORS.get(kind)
    if validator is not None:
        _load(validator)(url.strip(), local=local)
    return kind


def _load(target: str) -> Callable[..., Any]:
    module_name, _, attr = target.partition(":")
    module = importlib.import_module(module_name)
    return getattr(module, attr)  # type: ignore[no-any-return]


def board_for_url(url: str, **options: Any) -> Board:
    """Build (but do not open) the :class:`Board` for ``url``.

    ``options`` are passed to the transport (e.g. ``plant=`` for simulated boards,
    ``baudrate=`` for serial). Raises :class:`LinkUrlError` for a bad URL.
    """
    kind = link_scheme(url)
    target = _SERIAL_FACTORY if kind == "serial" else _SCHEMES[kind]
    factory: BoardFactory = _load(target)
    return factory(url, **options)
