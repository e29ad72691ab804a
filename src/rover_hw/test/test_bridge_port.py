"""The bridge takes a serial server on the network only when allow_network_port says so: such
servers (rfc2217://, socket://) take any client, with no authentication."""
from __future__ import annotations

import pytest
import rclpy
from rclpy.lifecycle import TransitionCallbackReturn
from rclpy.parameter import Parameter

from rover_hw.bridge_node import BridgeNode, is_network_port


def test_network_ports_are_told_apart():
    assert is_network_port('rfc2217://rover1.local:4000')
    assert is_network_port('SOCKET://10.0.0.2:7000')
    assert not is_network_port('/dev/ttyUSB0')
    assert not is_network_port('loop://')
    assert not is_network_port('/dev/serial/by-id/usb-FTDI_rover://odd')


@pytest.fixture
def ctx():
    c = rclpy.Context()
    rclpy.init(context=c)
    yield c
    c.try_shutdown()


@pytest.mark.parametrize('allow', [False, True])
def test_a_network_port_needs_allow_network_port(ctx, allow):
    node = BridgeNode(context=ctx, parameter_overrides=[
        Parameter('port', value='rfc2217://127.0.0.1:9'),
        Parameter('allow_network_port', value=allow)])
    opened = []

    def fake_open() -> None:
        opened.append(node.values['port'])
        raise OSError('nothing listens there')
    node._open = fake_open
    try:
        # refused before any connection unless allowed; allowed, it tries (and fails here)
        assert node.on_configure(None) == TransitionCallbackReturn.FAILURE
        assert opened == (['rfc2217://127.0.0.1:9'] if allow else [])
    finally:
        node.destroy_node()
