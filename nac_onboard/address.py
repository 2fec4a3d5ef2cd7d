"""HOST:PORT addresses as written in configs, scenarios and command lines: the one parser."""

from __future__ import annotations

from nac_onboard.errors import BadInput


def parse_host_port(text: str, what: str, *, allow_port_zero: bool = False) -> tuple[str, int]:
    """(host, port) from 'HOST:PORT' (IPv6 hosts in brackets); port 0 ("any free port") only for a listener that
    allows it. Raises BadInput naming `what` and the text."""
    host, sep, port = str(text).rpartition(":")
    lowest = 0 if allow_port_zero else 1
    if not sep or not host or not port.isdigit() or not lowest <= int(port) <= 65535:
        raise BadInput(f"{what}: expected HOST:PORT with a port {lowest}-65535, got {text!r}")
    return host.strip("[]"), int(port)
