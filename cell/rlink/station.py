"""A cell node's host side, sans IO: which of its robots are stopped and why, from the events it gets.

The data plane's and the robots' nodes each hand their events to a Station,
which turns them into Orders (stop these robots, resume those) and runs the
beacon watchdog: once beacons have been heard, silence for `watchdog_s` stops
every robot (reason WATCHDOG), and the next beacon resumes the robots the
watchdog stopped, and only those.  A stop ordered by ESTOP or STOP holds until
a RESUME names the robot.  A bad payload is counted, never raised.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from cell.rlink import events
from cell.rlink.events import EventError, Reason
from cell.rlink.packet import EventType, Packet


@dataclass(frozen=True)
class Order:
    stop: bool  # False: resume
    robots: list[int]
    reason: Reason
    emergency: bool = False  # ESTOP (the drives brake by themselves) rather than STOP
    requester: int = 0  # node address the reports go to
    token: int = 0


@dataclass
class StationCounters:
    estops: int = 0
    stops: int = 0
    resumes: int = 0
    beacons: int = 0
    watchdog_trips: int = 0
    bad_events: int = 0
    ignored: int = 0  # events that name none of this node's robots, or types it does not take


@dataclass
class Station:
    robots: set[int]
    watchdog_ns: int = 0  # 0: no watchdog
    stopped: dict[int, Reason] = field(default_factory=dict)
    counters: StationCounters = field(default_factory=StationCounters)
    last_beacon_ns: int | None = None
    hub_clock_offset_ns: int = 0  # the hub's clock minus ours, from the last beacon

    def on_event(self, p: Packet, now_ns: int) -> Order | None:
        c = self.counters
        try:
            if p.type in (EventType.ESTOP, EventType.STOP, EventType.RESUME, EventType.START):
                named = events.decode_set(p.payload).ids(self.robots)
            elif p.type == EventType.BEACON:
                self.hub_clock_offset_ns = events.decode_beacon(p.payload) - now_ns
                c.beacons += 1
                self.last_beacon_ns = now_ns
                lost = [r for r, why in self.stopped.items() if why == Reason.WATCHDOG]
                return self._resume(lost, Reason.BEACON, p) if lost else None
            else:
                c.ignored += 1
                return None
        except EventError:
            c.bad_events += 1
            return None
        if not named:
            c.ignored += 1
            return None
        token = events.decode_set(p.payload).token
        if p.type in (EventType.ESTOP, EventType.STOP):
            emergency = p.type == EventType.ESTOP
            if emergency:
                c.estops += 1
            else:
                c.stops += 1
            return self.stop(named, emergency, p.src, token)
        c.resumes += 1
        return self._resume(named, Reason.RESUME, p, token)

    def stop(self, robots: list[int], emergency: bool, requester: int = 0, token: int = 0) -> Order:
        """The order for an e-stop or stop of these robots (from an event, or the hub's account of the
        ones this node missed: LeafNode.restore), held until a resume names them."""
        reason = Reason.ESTOP if emergency else Reason.STOP
        for r in robots:
            # an e-stop outranks a stop; a commanded stop outranks the watchdog's
            if self.stopped.get(r) != Reason.ESTOP:
                self.stopped[r] = reason
        return Order(True, robots, reason, emergency, requester, token)

    def _resume(self, robots: list[int], reason: Reason, p: Packet, token: int = 0) -> Order:
        for r in robots:
            self.stopped.pop(r, None)
        return Order(False, robots, reason, requester=p.src, token=token)

    def check(self, now_ns: int) -> Order | None:
        """The watchdog: an order to stop every robot once the beacon has been silent too long."""
        if not self.watchdog_ns or self.last_beacon_ns is None:
            return None  # not armed until the first beacon
        if now_ns - self.last_beacon_ns < self.watchdog_ns:
            return None
        fresh = sorted(r for r in self.robots if r not in self.stopped)
        self.last_beacon_ns = None  # tripped: re-armed by the next beacon
        if not fresh:
            return None
        self.counters.watchdog_trips += 1
        for r in fresh:
            self.stopped[r] = Reason.WATCHDOG
        return Order(True, fresh, Reason.WATCHDOG)

    def as_dict(self) -> dict[str, float]:
        c = self.counters
        return {
            "estops": c.estops,
            "stops": c.stops,
            "resumes": c.resumes,
            "beacons": c.beacons,
            "watchdog_trips": c.watchdog_trips,
            "bad_events": c.bad_events,
            "stopped": len(self.stopped),
        }
