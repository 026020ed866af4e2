"""The robots' side of the cell: their groups built from the config, their announcements, the
Publisher that tells the bus what they do (truth, events), and their Responsive Link node (stops and
resumes read between ticks).  Served by services/robots.py.
"""

from __future__ import annotations

import time
from collections import defaultdict
from collections.abc import Callable
from dataclasses import replace

import numpy as np

from cell.bus import Bus
from cell.bus.envelope import put_arrays
from cell.config import CellConfig, RobotConfig, parse_host_port
from cell.rlink.events import Reason, RobotState, StateReport
from cell.rlink.leaf import LeafNode
from cell.rlink.packet import EventType, Kind
from cell.rlink.station import Order
from cell.robot.drive import HOLD_ESTOP, HOLD_UR
from cell.robot.emulator import RobotGroup
from cell.robot.truthcodec import TYPE_NAME as TRUTH
from cell.robot.truthcodec import truths_for
from cell.timer import realtime_offset
from cell.v1 import robot_pb2

ANNOUNCE_S = 2.0
ANNOUNCE_SLICE = 32  # robots announced at once (services/robots.py spreads the rest over ANNOUNCE_S)
Publish = Callable[[str, object], None]
WAKE_HZ = 20  # how often a group ticking in C wakes its Python (besides stops, resumes and clients)
_PROVIDED_BY = {"ur": "cell.ur.remote"}  # the group backends this package knows of, and their home
STILL_RAD_S = 1e-3  # a stopped robot stands still once every joint is slower than this


GroupFactory = Callable[[RobotConfig, CellConfig, str, Publish | None], RobotGroup]
# backends whose robot is a group of its own, provided by a package above this one ("ur": a real UR
# controller driven by cell.ur.remote's daemon, registered there), as python-can's BACKENDS
GROUP_BACKENDS: dict[str, GroupFactory] = {}


def register_group_backend(name: str, factory: GroupFactory) -> None:
    """Robots of backend `name` are each a group of their own, built by factory(robot, config, the
    address they bind, publish)."""
    GROUP_BACKENDS[name] = factory


def build_groups(config: CellConfig, publish: Publish | None = None) -> list[RobotGroup]:
    """This host's robots, one group per (backend, model, rates, socket), and one per robot of a
    group backend (GROUP_BACKENDS: "ur", its daemon telling the bus through `publish`); they bind
    this host's address (in a cell of one host: the data plane's)."""
    by_key: dict[tuple, list[RobotConfig]] = defaultdict(list)
    for r in config.local_robots():
        if r.backend in _PROVIDED_BY and r.backend not in GROUP_BACKENDS:
            raise ValueError(f"robot {r.name}: backend {r.backend!r} is not registered "
                             f"(import {_PROVIDED_BY[r.backend]} first)")  # fmt: skip
        by_key[
            (
                r.backend,
                r.model,
                r.status_hz,
                r.command_hz,
                r.socket,
                r.tick,
                r.id if r.backend in GROUP_BACKENDS else 0,
            )
        ].append(r)
    here = config.here()
    host = here.address if here is not None else parse_host_port(config.dataplane.listen)[0]
    if config.dataplane.runs.in_kernel and here is None:  # the switch's namespace is not ours: its veth
        host = config.dataplane.switch.host_addr
    groups: list[RobotGroup] = []
    try:
        for robots in by_key.values():
            factory = GROUP_BACKENDS.get(robots[0].backend)
            if factory is not None:
                groups.append(factory(robots[0], config, host, publish))
            else:
                groups.append(RobotGroup(robots, config.dataplane.address, host=host))
    except BaseException:
        for g in groups:
            g.close()
        raise
    return groups


def build_emulated_controllers(config: CellConfig) -> list[RobotGroup]:
    """The UR controllers this host emulates for its robots of backend "ur" with ur_emulate set: arms
    that offer only their UR interfaces (no datagrams), each driven through its own daemon."""
    robots = [replace(r, backend=r.ur_emulate, ur_emulate="") for r in config.local_robots() if r.ur_emulate]
    by_key: dict[tuple, list[RobotConfig]] = defaultdict(list)
    for r in robots:
        by_key[(r.backend, r.model, r.status_hz, r.command_hz, r.tick)].append(r)
    groups: list[RobotGroup] = []
    try:
        groups.extend(RobotGroup(rs, config.dataplane.address, datagrams=False) for rs in by_key.values())
    except BaseException:
        for g in groups:
            g.close()
        raise
    return groups


def announcements(group: RobotGroup, dataplane: str) -> list[robot_pb2.RobotAnnounce]:
    return [announcement(group, row, dataplane) for row in range(group.n)]


def announcement(group: RobotGroup, row: int, dataplane: str) -> robot_pb2.RobotAnnounce:
    """One robot's (a fleet's robot answers its own `announce` without building its 200 fellows')."""
    lim = group.arm.limits
    r = group.robots[row]
    origin = group.origin_ns + realtime_offset() if group.origin_ns else 0  # (the process's one offset)
    return robot_pb2.RobotAnnounce(
        robot_id=r.id,
        name=r.name,
        model=r.model,
        backend=r.backend,
        joints=group.dof,
        q_min=lim.q_min,
        q_max=lim.q_max,
        v_max=lim.v_max,
        a_max=lim.a_max,
        udp_address=group.robot_address(row),
        status_hz=r.status_hz,
        command_hz=r.command_hz,
        dataplane=dataplane,
        window_origin_ns=origin,
    )


class Publisher:
    """What one group tells the bus after each tick."""

    def __init__(
        self, bus: Bus, group: RobotGroup, node: RobotsNode | None = None, ur=None, full_rate: bool = False
    ) -> None:
        """full_rate: ground truth every tick whatever truth_hz says (a bag is recorded)."""
        self.bus = bus
        self.node = node
        self.ur = ur  # the group's UR interfaces (cell.ur.server.URInterfaces), told of every tick
        hz = group.robots[0].status_hz if full_rate else group.robots[0].truth_hz
        self.every = max(1, round(group.robots[0].status_hz / hz)) if hz > 0 else 0
        self.names = [r.name for r in group.robots]
        self.topics = [f"truth/{name}" for name in self.names]
        # each arm's RobotTruth, encoded in C where it builds (a fleet's truth is one GroupTruth)
        self.truths = None if group.shared else truths_for(group)
        self.ids = robot_pb2.GroupTruth(robot_id=group.ids.tolist()).SerializeToString()  # (a fleet's)
        self.outputs = group.digital_out.copy()  # the digital outputs the bus was last told of
        # a group ticking in C's thread is read on the truth's grid (and the Responsive Link node's look
        # for robots standing still: at 50 Hz at least), woken for it at WAKE_HZ: each wake-up costs
        # more than the messages it sends (five truths of 100 Hz a wake, not one or two)
        status_hz = group.robots[0].status_hz
        group.read_every = min(self.every or status_hz, max(1, status_hz // 50))
        group.wake_every = max(group.read_every, status_hz // WAKE_HZ)
        # ... and on every tick while the node waits for a stopped robot to stand (it reports STILL)
        others = group.busy
        if node is not None:
            group.busy = lambda: bool(node.waiting) or (others is not None and others())

    def __call__(self, group: RobotGroup, stopping: np.ndarray, resuming: np.ndarray) -> None:
        if self.node is not None:
            self.node.after_tick(group)
        if self.ur is not None:
            self.ur.after_tick(group, stopping, resuming)
        now = time.monotonic_ns()
        if (group.digital_out != self.outputs).any():
            self._outputs(group, now)
        tick_ns = round((group.state_time - group.period) * 1e9)  # (the tick it happened in: its deadline)
        for rows, kind, text in (
            (stopping, robot_pb2.RobotEvent.KIND_PROTECTIVE_STOP, "no command for the watchdog's windows"),
            (resuming, robot_pb2.RobotEvent.KIND_RESUMED, "commands resumed"),
        ):
            for row in rows:
                r = group.robots[row]
                ev = robot_pb2.RobotEvent(robot_id=r.id, name=r.name, kind=kind, text=text, t_ns=tick_ns)
                self.bus.publish(f"events/robot/{r.name}", ev)
        if self.every and group.tick_no % self.every == 0:
            at = round(group.state_time * 1e9)  # CLOCK_MONOTONIC ns of the state, not of publishing
            if group.shared:  # a fleet: every robot in one message
                answers, mean_us, max_us = group.counters.answers.take_window()
                msg = robot_pb2.GroupTruth(
                    t_ns=at,
                    tick=group.tick_no,
                    joints=group.dof,
                    answers=answers,
                    answer_us_mean=mean_us,
                    answer_us_max=max_us,
                )
                msg.MergeFromString(self.ids)
                put_arrays(msg, q=group.q.ravel(), stopped=group.stopped)
                self.bus.publish(f"fleet/{self.names[0]}", msg)
                return
            assert self.truths is not None  # (not a fleet)
            for topic, raw in zip(self.topics, self.truths(group, at), strict=True):
                self.bus.publish_serialized(topic, TRUTH, raw)

    def _outputs(self, group: RobotGroup, now: int) -> None:
        """Digital outputs that changed, as events: none is missed, however short (truth is sampled)."""
        for row in np.flatnonzero(group.digital_out != self.outputs):
            was, bits = int(self.outputs[row]), int(group.digital_out[row])
            changed = [n for n in range(64) if (was ^ bits) >> n & 1]
            text = ", ".join(f"{output_name(n)} {'on' if bits >> n & 1 else 'off'}" for n in changed)
            r = group.robots[row]
            ev = robot_pb2.RobotEvent(
                robot_id=r.id, name=r.name, kind=robot_pb2.RobotEvent.KIND_OUTPUTS, text=text, t_ns=now,
                digital_out=bits,
            )  # fmt: skip
            self.bus.publish(f"events/robot/{r.name}", ev)
        self.outputs[:] = group.digital_out


class RobotsNode(LeafNode):
    """The robots' Responsive Link node: halts and releases drives, reports when robots stand."""

    role = "robots"

    def __init__(self, groups: list[RobotGroup], config: CellConfig) -> None:
        self.rows = {int(rid): (g, row) for g in groups for row, rid in enumerate(g.ids)}
        super().__init__(config, set(self.rows))
        self.waiting: dict[int, tuple[int, Reason]] = {}  # robot -> (when its stop came, why)
        self.halt_us: list[float] = []  # event read -> drives halted
        self.still_ms: list[float] = []  # stop order -> standing still

    def apply(self, order: Order) -> None:
        brake = order.emergency or order.reason == Reason.WATCHDOG
        now = time.monotonic_ns()
        for rid in order.robots:
            g, row = self.rows[rid]
            if order.stop:
                if brake:
                    g.drives.halt(np.array([row]))
                self.waiting.setdefault(rid, (now, order.reason))
                if g.native is not None:  # (C's thread wakes this on every tick from now on)
                    g.native.state.wake_every = 1
                self.report(rid, RobotState.STOPPING, order.reason)
            else:
                g.drives.halt(np.array([row]), on=False)
                self.waiting.pop(rid, None)
                self.report(rid, RobotState.RESUMED, order.reason)
        if order.stop and brake:
            self.halt_us.append((time.perf_counter_ns() - self.link.arrived_ns) / 1e3)
            del self.halt_us[:-1024]

    def report(self, robot: int, state: RobotState, reason: Reason, detail: int = 0) -> None:
        payload = StateReport(robot, state, reason, detail).encode()
        self.link.send(Kind.EVENT, self.hub, EventType.STATE, payload, priority=2)

    def after_tick(self, group: RobotGroup) -> None:
        """Robots that were stopped and now stand: reported once."""
        if not self.waiting:
            return
        now = time.monotonic_ns()
        for rid, (since, why) in list(self.waiting.items()):
            g, row = self.rows[rid]
            if g is not group:
                continue
            if np.abs(g.qd[row]).max() < STILL_RAD_S and not g.velocity[row].any():
                del self.waiting[rid]
                self.still_ms.append((now - since) / 1e6)
                del self.still_ms[:-1024]
                self.report(rid, RobotState.STILL, why, (now - since) // 1000)

    def counters(self) -> dict[str, float]:
        out = super().counters()
        if self.halt_us:
            out["rlink.halt_us_max"] = max(self.halt_us)
        if self.still_ms:
            out["rlink.still_ms_max"] = max(self.still_ms)
        return out


def output_name(bit: int) -> str:
    """A UR's name for digital output `bit` of actual_digital_output_bits: DO0-7, CO0-7 (configurable),
    TO0-1 (tool)."""
    if bit < 8:
        return f"DO{bit}"
    return f"CO{bit - 8}" if bit < 16 else f"TO{bit - 16}"


def counters(groups: list[RobotGroup]) -> dict[str, float]:
    total: dict[str, float] = defaultdict(float)
    for g in groups:
        for k, v in g.counters.as_dict().items():
            total[k] = max(total[k], v) if k.startswith(("lateness", "answer")) else total[k] + v
    total["robots"] = sum(g.n for g in groups)
    return dict(total)


# what a robot is doing, as `cell status` shows it (a code in the robots service's counters,
# robot.<name>.state; cell.status.ROBOT_STATES names them)
STANDING, MOVING, PROTECTIVE_STOP, ESTOPPED, UR_HELD, UR_SCRIPT, SILENT = range(7)


def robot_states(groups: list[RobotGroup]) -> dict[str, float]:
    """Each robot's state now (robot.<name>.state): the first that holds of e-stopped, held by its
    UR state (powered off, braked, safety-stopped), protective stop, mute, under a URScript program,
    moving, standing."""
    out: dict[str, float] = {}
    now = time.monotonic()
    for g in groups:
        d = g.drives
        for row, r in enumerate(g.robots):
            if d.holds[row] & HOLD_ESTOP:
                state = ESTOPPED
            elif d.holds[row] & HOLD_UR:
                state = UR_HELD
            elif d.stopped[row]:
                state = PROTECTIVE_STOP
            elif g.silent_until[row] > now:
                state = SILENT
            elif d.scripted[row]:
                state = UR_SCRIPT
            elif np.abs(g.backend.qd[row]).max() >= STILL_RAD_S:
                state = MOVING
            else:
                state = STANDING
            out[f"robot.{r.name}.state"] = state
    return out


def has_node(config: CellConfig) -> bool:
    """The robots' Responsive Link node runs beside the hub (in a cell of several hosts, on its host;
    robots elsewhere stop on the data plane's stop ramp)."""
    return not config.hosts or "rlink" in config.services.run
