"""Loopback ports for tests that run the example configuration (its `tc_udp` names a fixed port)."""
from __future__ import annotations

import socket

EXAMPLE_TC_UDP = 'tc_udp = "127.0.0.1:50511"'


def free_udp_port() -> int:
    """A UDP port on 127.0.0.1 that was free a moment ago (bound to port 0, then released)."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def own_tc_port(text: str) -> str:
    """The example configuration with its telecommand port replaced by a free one (tests run in parallel)."""
    assert EXAMPLE_TC_UDP in text
    return text.replace(EXAMPLE_TC_UDP, f'tc_udp = "127.0.0.1:{free_udp_port()}"')
