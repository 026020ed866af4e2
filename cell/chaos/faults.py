"""The faults a chaos campaign injects, and what the cell promises under each.

A fault acts on the running cell from outside, as the world would: a signal
to a service's process (SIGKILL: it dies; SIGSTOP ... SIGCONT: it hangs),
the bus forwarder frozen for seconds, delay and loss on the controller's bus
link (cell.bus.delay), a robot that stops answering (robot/<name>.silence).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, field

# services on the packet path: the robots' commands stop when one of them does
PACKET_PATH = ("dataplane", "robots")
# the services of the default cell a campaign faults, in the order it faults them
SERVICES = ("bus", "dataplane", "robots", "controller", "skills", "snp", "recorder", "rlink", "vision")


@dataclass(frozen=True)
class Action:
    """One thing done to the cell: kind is kill, stop (SIGSTOP for `seconds`), link (the controller's
    bus link slowed for `seconds`), silence (a robot mute for `seconds`), switch-down (the XDP
    switch's veth port down for `seconds`: every robot's cable at once) or detach (the XDP program
    taken off the switch's port, as `ip link set dev ... xdpgeneric off` does; watched `seconds`)."""

    kind: str
    target: str  # a service, or for silence a robot's name
    seconds: float = 0.0


@dataclass(frozen=True)
class Fault:
    name: str
    actions: tuple[Action, ...]
    promises: tuple[str, ...]  # keys of PROMISES that apply
    figures: dict[str, float] = field(default_factory=dict)

    @property
    def services(self) -> set[str]:
        return {a.target for a in self.actions if a.kind in ("kill", "stop")}

    @property
    def seconds(self) -> float:
        return max((a.seconds for a in self.actions), default=0.0)

    @property
    def touches_packet_path(self) -> bool:
        return bool(self.services & set(PACKET_PATH)) or any(a.kind == "silence" for a in self.actions)


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
    services = {a.target for a in actions if a.kind in ("kill", "stop")}
    silent = any(a.kind == "silence" for a in actions)
    cut = any(a.kind == "switch-down" for a in actions)  # (every robot's cable at once)
    if services & set(PACKET_PATH) or silent or cut:
        out += ["answered_1s"]
    if services & {"dataplane"} and not services & {"robots"}:
        out += ["kernel_answers" if in_kernel else "stop_windows"]
    if cut:
        out += ["stop_windows"]
    if not services & {*PACKET_PATH, "rlink"} and not silent and not cut:
        out += ["packet_path"]
    if any(a.kind == "detach" for a in actions):
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
    out = [fault(f"kill:{s}", Action("kill", s)) for s in SERVICES]
    out += [fault(f"hang:{s}", Action("stop", s, hang_s)) for s in SERVICES if s != "bus"]
    out.append(fault("bus-gone", Action("stop", "bus", bus_gone_s)))
    out.append(fault("controller-link", Action("link", "controller", link_s)))
    mute = [r for r in robots if r not in ur_robots][-1]  # (an emulated arm: its cable pulled)
    out.append(fault(f"mute:{mute}", Action("silence", mute, hang_s)))
    out += [fault(f"ur-controller-gone:{r}", Action("silence", r, hang_s)) for r in ur_robots]
    out += [
        fault("kill:dataplane+controller", Action("kill", "dataplane"), Action("kill", "controller")),
        fault(
            "bus-gone+controller-link",
            Action("stop", "bus", bus_gone_s),
            Action("link", "controller", link_s),
        ),
        fault("kill:skills+mute", Action("kill", "skills"), Action("silence", mute, hang_s)),
    ]
    if in_kernel:  # the switch's own faults: its port to the robots down for 2 s, its program detached
        out.append(fault("switch-down", Action("switch-down", "dataplane", 2.0)))
        out.append(fault("xdp-detached", Action("detach", "dataplane", 1.0)))
    return out
