"""The faults a chaos campaign injects, and what the cell promises under each.

A fault acts on the running cell from outside, as the world would: a signal
to a service's process (SIGKILL: it dies; SIGSTOP ... SIGCONT: it hangs),
the bus forwarder frozen for seconds, delay and loss on the controller's bus
link (cell.bus.delay), a robot that stops answering (robot/<name>.silence).
"""

from __future__ import annotations

import asyncio
import contextlib
import functools
import os
import signal
from dataclasses import dataclass, field
from typing import ClassVar, Protocol

from cell.bus import Bus
from cell.bus.delay import DelayLink
from cell.config import CellConfig
from cell.v1 import robot_pb2

LINK = (0.050, 0.020, 0.05)  # the controller's slow link: delay, jitter (s), loss
# services on the packet path: the robots' commands stop when one of them does
PACKET_PATH = ("dataplane", "robots")
# the services of the default cell a campaign faults, in the order it faults them
SERVICES = ("bus", "dataplane", "robots", "controller", "skills", "snp", "recorder", "rlink", "vision")


class Target(Protocol):
    """What an action acts on: the campaign's running cell."""

    config: CellConfig
    link: DelayLink  # the controller's bus link

    def switch_port(self, *setting: str) -> None:
        """`ip link set` on the XDP switch's port to the robots."""


@dataclass(frozen=True)
class Action:
    """One thing done to the cell, to `target` (a service, or a robot's name), for `seconds`: inject()
    starts it, end() undoes what does not end by itself (end() twice is harmless)."""

    target: str
    seconds: float = 0.0
    kind: ClassVar[str]  # (the catalogue's word for it)

    async def inject(self, cell: Target, pids: dict[str, int]) -> None:
        raise NotImplementedError

    def end(self, cell: Target, pids: dict[str, int]) -> None:
        return None


@dataclass(frozen=True)
class Kill(Action):
    """The service's process SIGKILLed: it dies, its supervisor restarts it."""

    kind = "kill"

    async def inject(self, cell: Target, pids: dict[str, int]) -> None:
        os.kill(pids[self.target], signal.SIGKILL)


@dataclass(frozen=True)
class Hang(Action):
    """The service's process SIGSTOPped for `seconds`, then SIGCONTinued: it hangs."""

    kind = "stop"

    async def inject(self, cell: Target, pids: dict[str, int]) -> None:
        os.kill(pids[self.target], signal.SIGSTOP)

    def end(self, cell: Target, pids: dict[str, int]) -> None:
        with contextlib.suppress(ProcessLookupError):
            os.kill(pids[self.target], signal.SIGCONT)


@dataclass(frozen=True)
class SlowLink(Action):
    """The controller's bus link slow and lossy (LINK) for `seconds`."""

    kind = "link"

    async def inject(self, cell: Target, pids: dict[str, int]) -> None:
        cell.link.delay, cell.link.jitter, cell.link.loss = LINK

    def end(self, cell: Target, pids: dict[str, int]) -> None:
        cell.link.delay = cell.link.jitter = cell.link.loss = 0.0


@dataclass(frozen=True)
class Silence(Action):
    """A robot mute for `seconds` (robot/<name>.silence): its cable pulled, or its UR controller gone."""

    kind = "silence"

    async def inject(self, cell: Target, pids: dict[str, int]) -> None:
        async with Bus.connect(cell.config.bus, "chaos-silence") as bus:
            req = robot_pb2.SilenceRequest(robot=self.target, seconds=self.seconds)
            await bus.request(f"robot/{self.target}", "silence", req)


@dataclass(frozen=True)
class SwitchDown(Action):
    """The XDP switch's veth port to the robots down for `seconds`: every robot's cable at once."""

    kind = "switch-down"

    async def inject(self, cell: Target, pids: dict[str, int]) -> None:
        await asyncio.to_thread(cell.switch_port, "down")

    def end(self, cell: Target, pids: dict[str, int]) -> None:
        cell.switch_port("up")


@dataclass(frozen=True)
class Detach(Action):
    """The XDP program taken off the switch's port (as `ip link set dev ... xdpgeneric off` does);
    watched `seconds` while the data plane attaches it again."""

    kind = "detach"

    async def inject(self, cell: Target, pids: dict[str, int]) -> None:
        await asyncio.to_thread(cell.switch_port, "xdpgeneric", "off")


ON_SERVICE = (Kill, Hang)  # the actions on a service's process


@dataclass(frozen=True)
class Fault:
    name: str
    actions: tuple[Action, ...]
    promises: tuple[str, ...]  # keys of PROMISES that apply
    figures: dict[str, float] = field(default_factory=dict)

    @property
    def services(self) -> set[str]:
        return {a.target for a in self.actions if isinstance(a, ON_SERVICE)}

    @property
    def seconds(self) -> float:
        return max((a.seconds for a in self.actions), default=0.0)

    @property
    def touches_packet_path(self) -> bool:
        return bool(self.services & set(PACKET_PATH)) or any(isinstance(a, Silence) for a in self.actions)


PROMISES = {
    "answered": "every waiting command answered done or error:stopped:<reason>; none timed out or failed",
    "answered_1s": "waiting commands answered error:stopped within 1 s of the fault",
    "completed": "a command answered done really ended at its goal (nothing acknowledged is lost)",
    "packet_path": "the packet path ran on: no protective stop, no trajectory dropped",
    "stop_windows": "robots on a stop within the watchdog's windows (+1 for the one under way)",
    "kernel_answers": "the XDP program answered on without its control plane: no robot protective-stopped",
    "reattached": "the data plane answered through its detached XDP program and attached it again",
    "no_lunge": "no unplanned motion: once at rest after the fault, robots stay at rest",
    "estop": "an e-stop issued during the fault stops every robot within its deadline (its braking from "
    "the speed it had, +60 ms); with the Responsive Link's hub down, the link's watchdog stops them",
    "status": "cell status shows the restart (count, last error) or the hang (stale), then ok",
    "recovered": "motions work again on every robot after the fault",
}
_BASE = ("answered", "completed", "no_lunge", "recovered")


def _promises(actions: tuple[Action, ...], in_kernel: bool = False) -> tuple[str, ...]:
    """in_kernel: the data plane is an XDP program (examples/xdp.toml); its service's process is only
    its control plane, and the program answers the robots on while that process is dead or hung."""
    out = list(_BASE)
    services = {a.target for a in actions if isinstance(a, ON_SERVICE)}
    silent = any(isinstance(a, Silence) for a in actions)
    cut = any(isinstance(a, SwitchDown) for a in actions)  # (every robot's cable at once)
    if services & set(PACKET_PATH) or silent or cut:
        out += ["answered_1s"]
    if services & {"dataplane"} and not services & {"robots"}:
        out += ["kernel_answers" if in_kernel else "stop_windows"]
    if cut:
        out += ["stop_windows"]
    if not services & {*PACKET_PATH, "rlink"} and not silent and not cut:
        out += ["packet_path"]
    if any(isinstance(a, Detach) for a in actions):
        out += ["reattached"]
    if "robots" not in services:  # (a dead or hung arm emulator is not an arm the e-stop can judge)
        out += ["estop"]
    if services:
        out += ["status"]
    return tuple(out)


def _fault(name: str, *actions: Action, in_kernel: bool = False) -> Fault:
    return Fault(name, actions, _promises(actions, in_kernel))


def catalogue(
    robots: list[str],
    hang_s: float = 3.5,
    bus_gone_s: float = 5.0,
    link_s: float = 4.0,
    ur_robots: tuple[str, ...] = (),
    in_kernel: bool = False,
) -> list[Fault]:
    """Every fault of a campaign round: each service killed, each hung, the bus gone, the controller's
    link slow and lossy, a robot mute, the UR controller of each robot of backend "ur" (`ur_robots`)
    gone (its daemon's link to it cut: the same request, robot/<name>.silence); then a few of them
    together.  in_kernel: the data plane is an XDP program (see _promises)."""

    fault = functools.partial(_fault, in_kernel=in_kernel)
    out = [fault(f"kill:{s}", Kill(s)) for s in SERVICES]
    out += [fault(f"hang:{s}", Hang(s, hang_s)) for s in SERVICES if s != "bus"]
    out.append(fault("bus-gone", Hang("bus", bus_gone_s)))
    out.append(fault("controller-link", SlowLink("controller", link_s)))
    mute = [r for r in robots if r not in ur_robots][-1]  # (an emulated arm: its cable pulled)
    out.append(fault(f"mute:{mute}", Silence(mute, hang_s)))
    out += [fault(f"ur-controller-gone:{r}", Silence(r, hang_s)) for r in ur_robots]
    out += [
        fault("kill:dataplane+controller", Kill("dataplane"), Kill("controller")),
        fault(
            "bus-gone+controller-link",
            Hang("bus", bus_gone_s),
            SlowLink("controller", link_s),
        ),
        fault("kill:skills+mute", Kill("skills"), Silence(mute, hang_s)),
    ]
    if in_kernel:  # the switch's own faults: its port to the robots down for 2 s, its program detached
        out.append(fault("switch-down", SwitchDown("dataplane", 2.0)))
        out.append(fault("xdp-detached", Detach("dataplane", 1.0)))
    return out
