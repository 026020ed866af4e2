"""The data plane's control-plane API, for controllers: load and remove TPs, switch, start, read state."""

from __future__ import annotations

from collections.abc import Iterable, Sequence

import numpy as np

from cell.bus import Bus
from cell.dataplane.tables import TP, TPBatch
from cell.dataplane.wire import encode_keys, encode_tps
from cell.v1 import dataplane_pb2


class DataplaneClient:
    """Requests over the bus to service "dataplane"; errors come back as RemoteError(code, reason)."""

    def __init__(
        self, bus: Bus, service: str = "dataplane", timeout: float | None = None, controller: int = 0
    ) -> None:
        self.bus = bus
        self.service = service
        self.timeout = timeout
        self.controller = controller  # a controller's id, sent with its updates (TableUpdate.controller)

    async def update(
        self,
        insert: Iterable[TP] | TPBatch = (),
        remove: Iterable[tuple[int, int]] | np.ndarray = (),
        switches: Iterable[tuple[int, int, int | None]] = (),
        registers: Iterable[tuple[int, int | None, int]] = (),
        flush: Iterable[int] = (),
    ) -> dataplane_pb2.UpdateReply:
        """One atomic batch (see Tables.update): applied whole, or refused whole with a reason.  The
        robots in `flush` lose every TP and their registers first (a controller taking over)."""
        req = dataplane_pb2.TableUpdate(flush_robots=flush, controller=self.controller)
        encode_tps(insert if isinstance(insert, TPBatch) else TPBatch.of(list(insert)), req.insert)
        encode_keys(remove, req.remove)
        tp_id: int | None  # (a switch's TP; a register's, None to clear)
        for robot, tp_id, nxt in switches:
            req.switches.add(robot_id=robot, tp_id=tp_id, next_id=nxt or 0, unset=nxt is None)
        for robot, tp_id, next_time in registers:
            req.registers.add(robot_id=robot, tp_id=tp_id or 0, next_time_ns=next_time, clear=tp_id is None)
        reply = await self.bus.request(self.service, "update", req, dataplane_pb2.UpdateReply, self.timeout)
        assert isinstance(reply, dataplane_pb2.UpdateReply)
        return reply

    async def load_constants(
        self, c1: Sequence[float], c2: Sequence[float], n_bits: int, v_max: Sequence[float]
    ) -> dataplane_pb2.ConstantsReply:
        """New controller constants; the data plane regenerates its Transform and LimitVelocity tables."""
        req = dataplane_pb2.Constants(c1=c1, c2=c2, n_bits=n_bits, v_max=v_max)
        reply = await self.bus.request(
            self.service, "load_constants", req, dataplane_pb2.ConstantsReply, self.timeout
        )
        assert isinstance(reply, dataplane_pb2.ConstantsReply)
        return reply

    async def merge(self, robots: Sequence[int]) -> int:
        req = dataplane_pb2.MergeRequest(robot_ids=robots)
        reply = await self.bus.request(self.service, "merge", req, dataplane_pb2.MergeReply, self.timeout)
        return reply.entity

    async def state(
        self, robot_ids: Sequence[int] = (), robots_only: bool = False, timeout: float | None = None
    ) -> dataplane_pb2.DataplaneState:
        """Registers and counters; robots_only leaves the counters out (a cheaper poll)."""
        req = dataplane_pb2.StateRequest(robot_ids=robot_ids, robots_only=robots_only)
        timeout = self.timeout if timeout is None else timeout
        reply = await self.bus.request(self.service, "state", req, dataplane_pb2.DataplaneState, timeout)
        assert isinstance(reply, dataplane_pb2.DataplaneState)
        return reply
