"""The cell bus: protobuf messages over ZeroMQ through one XSUB/XPUB forwarder.

async with Bus.connect(config.bus, "my-service") as bus:
    bus.publish("events/hello", msg)
    sub = await bus.subscribe("status/")
    reply = await bus.request("dataplane", "insert_tps", req, InsertReply)
"""

from cell.bus.envelope import Envelope, EnvelopeError, GapCounter, Kind
from cell.bus.forwarder import Forwarder, ForwarderStats
from cell.bus.node import (
    Bus,
    BusError,
    BusRefused,
    BusTimeout,
    BusUnavailable,
    FaultCode,
    RemoteError,
    RpcFault,
    ServiceDown,
    Subscription,
)

__all__ = [
    "Bus",
    "BusError",
    "BusRefused",
    "BusTimeout",
    "BusUnavailable",
    "Envelope",
    "EnvelopeError",
    "FaultCode",
    "Forwarder",
    "ForwarderStats",
    "GapCounter",
    "Kind",
    "RemoteError",
    "RpcFault",
    "ServiceDown",
    "Subscription",
]
