"""The datagram sender (cell/robot/udp.py): what the network refuses is counted, never raised."""

from __future__ import annotations

import socket

import numpy as np
import pytest

from cell.robot import datagram, udp


@pytest.mark.parametrize("gso", [True, False])
def test_a_send_the_network_refuses_is_counted_unsent_with_its_reason(gso: bool) -> None:
    """A data plane stopping robots while their link is down (no route: ENETUNREACH) lost the rest
    of the stop to the exception; here the refusal is a broadcast without SO_BROADCAST (EACCES),
    which any host refuses the same way."""
    with socket.socket(type=socket.SOCK_DGRAM) as sock, socket.socket(type=socket.SOCK_DGRAM) as peer:
        peer.bind(("127.0.0.1", 0))
        sender = udp.Sender(sock, datagram.SIZE)
        sender.gso = sender.gso and gso
        buf = np.zeros(3 * datagram.SIZE, np.uint8).data
        assert sender.send(buf, ("255.255.255.255", 9)) == 0
        assert sender.errors == 1 and sender.last_error == "Permission denied"
        assert sender.send(buf, peer.getsockname()) == 3  # (the socket still sends)
        assert [len(peer.recv(4096)) for _ in range(3)] == [datagram.SIZE] * 3  # (GSO: segmented)
