"""Which addresses are loopback: the one rule for every server PackPilot opens (the dashboard,
the CAN hub), each of which listens on loopback unless told otherwise."""

from __future__ import annotations

import ipaddress
import socket


def is_loopback(addr: str) -> bool:
    """An IP address literal on the loopback network (names are not resolved here)."""
    try:
        return ipaddress.ip_address(addr.strip("[]").split("%")[0]).is_loopback
    except ValueError:
        return False


def resolves_to_loopback(host: str) -> bool:
    """Every address ``host`` resolves to is loopback (``localhost``, ``127.0.0.1``, ``::1``)."""
    try:
        infos = socket.getaddrinfo(host, None, type=socket.SOCK_STREAM)
    except (socket.gaierror, UnicodeError):
        return False
    return bool(infos) and all(is_loopback(str(i[4][0])) for i in infos)


__all__ = ["is_loopback", "resolves_to_loopback"]
