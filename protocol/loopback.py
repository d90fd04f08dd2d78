"""Whether an address stays on this host: loopback hosts, and the Host header check.

A host is *loopback* when it is the name ``localhost`` or an address in 127.0.0.0/8 or ::1
(``is_loopback``). Anything else (``*``, ``0.0.0.0``, ``::``, another address, a host name)
can be reached from the network: ``facewire send`` warns when it binds there without CURVE,
the live view (``receive --view``) refuses to, and ``facewire web`` refuses unless asked
(``--allow-remote``) and then warns.

DNS rebinding. A web page from anywhere can make a browser on this host send requests to a
name of its own that it then resolves to 127.0.0.1, and read the answers (same origin as
far as the browser knows). Such a request carries that name in its ``Host`` header, so a
server bound to loopback answers only requests whose Host names a loopback host
(``host_header_is_loopback``).
"""

from __future__ import annotations

import ipaddress
from urllib.parse import urlsplit

LOOPBACK_NAMES = ("localhost",)


def is_loopback(host: str) -> bool:
    """True for ``localhost`` and for addresses in 127.0.0.0/8 or ::1 (brackets allowed)."""
    host = host.strip("[]")
    if host.lower() in LOOPBACK_NAMES:
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def host_header_is_loopback(header: str | None) -> bool:
    """True when an HTTP ``Host`` header (``name[:port]``) names a loopback host."""
    if not header:
        return False
    try:
        name = urlsplit(f"//{header}").hostname
    except ValueError:  # e.g. an unbalanced bracket
        return False
    return name is not None and is_loopback(name)
