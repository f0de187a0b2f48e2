"""Links to a sensor (docs/architecture.md): one :class:`~hostlink.links.base.Link` interface, chosen by one string.

A link string is ``SCHEME:TARGET``; the scheme picks the transport module, which parses its own target:

========================  =====================================  =========================================
scheme                    module                                 example
========================  =====================================  =========================================
``serial``                ``hostlink.links.serial_link``         ``serial:/dev/ttyUSB0@921600``,
                                                                 ``serial:rfc2217://host:4000@115200``
``can``                   ``hostlink.links.can_link``            (see that module)
``modbus-tcp``            ``hostlink.links.modbus_link``         (see that module)
``modbus-rtu``            ``hostlink.links.modbus_link``         (see that module)
========================  =====================================  =========================================

Each transport module defines ``open_link(scheme: str, target: str, timeout_s: float) -> Link`` and raises
``UserError`` (one line) for a malformed target or an interface whose driver is not installed here (a python-can
interface without its vendor library), and ``LinkError`` when the port cannot be opened. Real ports and the
emulators (``hostlink emulate`` prints the string to use) are opened the same way.
"""

from __future__ import annotations

import importlib

from hostlink.errors import UserError
from hostlink.links.base import DEFAULT_TIMEOUT_S, CommandRefused, Link, LinkStats, MessageLink

__all__ = ["DEFAULT_TIMEOUT_S", "CommandRefused", "Link", "LinkStats", "MessageLink", "TRANSPORTS", "open_link"]

#: Link-string scheme -> module that implements it (imported on first use).
TRANSPORTS: dict[str, str] = {
    "serial": "hostlink.links.serial_link",
    "can": "hostlink.links.can_link",
    "modbus-tcp": "hostlink.links.modbus_link",
    "modbus-rtu": "hostlink.links.modbus_link",
}


def split_link_string(link: str) -> tuple[str, str]:
    """``"serial:/dev/pts/3@921600"`` -> ``("serial", "/dev/pts/3@921600")``; one-line UserError if malformed."""
    scheme, sep, target = str(link).partition(":")
    scheme = scheme.strip().lower()
    if not sep or not target or scheme not in TRANSPORTS:
        known = ", ".join(f"{s}:..." for s in TRANSPORTS)
        raise UserError(f"--link {link!r}: expected SCHEME:TARGET with a scheme among {known}")
    return scheme, target


def open_link(link, timeout_s: float = DEFAULT_TIMEOUT_S) -> Link:
    """Open the sensor link named by ``link`` (the ``--link`` option, e.g. ``serial:/dev/ttyUSB0@921600``), whose
    replies are awaited at most ``timeout_s`` [s]. Raises UserError (one line) for a malformed string or a transport
    missing from this build, LinkError when the port cannot be opened. Use as a context manager (closes it).
    ``link`` may also be a python-can bus the caller already opened (a ``can.BusABC``): the link then runs on it and
    leaves it open when closed (:func:`hostlink.links.can_link.link_on_bus`)."""
    if not isinstance(link, str):
        from hostlink.links.can_link import link_on_bus

        return link_on_bus(link, timeout_s)
    scheme, target = split_link_string(link)
    try:
        module = importlib.import_module(TRANSPORTS[scheme])
    except ModuleNotFoundError as exc:
        if exc.name == TRANSPORTS[scheme]:
            raise UserError(f"--link {link!r}: the {scheme} transport is not available in this build") from None
        raise
    return module.open_link(scheme, target, timeout_s)
