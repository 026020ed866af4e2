"""A bench's own XDP switch: a network namespace named after the bench and its pid (removed after),
and the [dataplane] settings that run the data plane in it."""

from __future__ import annotations

import os
from dataclasses import asdict
from typing import Any

from cell.config import XdpConfig

XDP_PORT = 50000  # the switch data plane's port


def xdp_switch(cpu: int = -1, tag: str = "cbx") -> XdpConfig:
    """A benchmark's own switch namespace, named tag + pid (removed afterwards); cpu: where the
    program runs (-1: on the CPU that sent the packet, the generator's)."""
    name = f"{tag}{os.getpid()}"[:12]
    host, switch = "10.198.0.1", "10.198.0.2"
    return XdpConfig(netns=name, veth=name, host_addr=host, switch_addr=switch, prefix=24, cpu=cpu)


def xdp_dataplane(net: XdpConfig) -> dict[str, Any]:
    """[dataplane] overrides for the XDP backend on this switch (listen on its end, XDP_PORT)."""
    return {"listen": f"{net.switch_addr}:{XDP_PORT}", "backend": "xdp", "xdp": asdict(net)}
