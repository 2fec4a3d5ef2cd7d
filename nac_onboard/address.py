"""HOST:PORT addresses as written in configs, scenarios and command lines: the one parser."""

from __future__ import annotations

import ipaddress

from nac_onboard.errors import BadInput


def parse_host_port(text: str, what: str, *, allow_port_zero: bool = False) -> tuple[str, int]:
    """(host, port) from 'HOST:PORT' (IPv6 hosts in brackets); port 0 ("any free port") only for a listener that
    allows it. Raises BadInput naming `what` and the text."""
    host, sep, port = str(text).rpartition(":")
    lowest = 0 if allow_port_zero else 1
    if not sep or not host or not port.isdigit() or not lowest <= int(port) <= 65535:
        raise BadInput(f"{what}: expected HOST:PORT with a port {lowest}-65535, got {text!r}")
    return host.strip("[]"), int(port)


def is_loopback(host: str) -> bool:
    """True for an address only this machine reaches (127.0.0.0/8, ::1, localhost)."""
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return host == "localhost"
