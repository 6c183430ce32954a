"""The test run talks over loopback alone (tests/conftest.py puts it in its own network
namespace where it can: as root, on the development machines and CI)."""

import os
import socket

import pytest

from .conftest import NETWORK_ISOLATED


@pytest.mark.skipif(os.geteuid() != 0, reason="a network namespace needs root here")
def test_the_run_sees_only_the_loopback_device():
    assert NETWORK_ISOLATED
    assert [name for _, name in socket.if_nameindex()] == ["lo"]
    with socket.socket() as server:
        server.bind(("127.0.0.1", 0))
        server.listen()
        with socket.create_connection(server.getsockname(), timeout=5):
            pass  # loopback is up
