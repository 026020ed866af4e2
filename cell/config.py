"""The cell's configuration: TOML merged over the embedded default (cell/default.toml).

Every default lives in default.toml, nowhere else; the dataclasses below only
say what each key must be.  Any unknown key or bad value raises ConfigError
naming the key and the file, which the CLI turns into exit code 2.

One module, over 600 lines, on purpose: the schema is one dataclass per TOML table, in the order
default.toml has them, so the two read side by side; the loader is the few functions after them.
"""

from __future__ import annotations

import copy
import ctypes
import functools
import ipaddress
import os
import re
import shutil
import tomllib
import types
from collections.abc import Callable
from dataclasses import asdict, dataclass, field, fields, is_dataclass, replace
from importlib import resources
from pathlib import Path
from typing import Any, Literal, TypeVar, Union, dataclass_transform, get_args, get_origin, get_type_hints

import tomli_w

from cell.models import MODELS, get

DEFAULT_SOURCE = "<embedded default>"
_NAME = re.compile(r"[a-z][a-z0-9_\-]{0,31}")
_ENTRY = re.compile(r"[A-Za-z_][\w.]*:[A-Za-z_]\w*")


class ConfigError(Exception):
    """A configuration that cannot be used; says which key of which file and why."""

    def __init__(self, source: str, key: str, problem: str) -> None:
        self.source, self.key, self.problem = source, key, problem
        where = f"{key}: " if key else ""
        super().__init__(f"config error in {source}: {where}{problem}")


# --- value checks: each returns a problem or None --------------------------------------------


def _positive(v: float) -> str | None:
    return None if v > 0 else f"must be > 0 (got {v})"


def _port(v: int) -> str | None:
    return None if 1 <= v <= 65535 else f"must be a port number 1..65535 (got {v})"


def _name(v: str) -> str | None:
    ok = _NAME.fullmatch(v)
    return None if ok else f"must be a name of lowercase letters, digits, '_' or '-' (got {v!r})"


def _host_port(v: str) -> str | None:
    try:
        parse_host_port(v)
    except ValueError as exc:
        return str(exc)
    return None


def _zmq_endpoint(v: str) -> str | None:
    if v.startswith("ipc://") and len(v) > 6:
        return None
    if v.startswith("tcp://"):
        return _host_port(v[6:])
    return f"must be tcp://HOST:PORT or ipc://PATH (got {v!r})"


def _cpus(v: list[int]) -> str | None:
    return None if all(c >= 0 for c in v) else f"must list CPU numbers >= 0 (got {v})"


def _rt_priority(v: int) -> str | None:
    return None if 0 <= v <= 99 else f"must be 0 (normal scheduling) or a SCHED_FIFO priority 1..99 (got {v})"


def _nice(v: int) -> str | None:
    return None if -20 <= v <= 19 else f"must be a nice value -20..19 (got {v})"


def _joint_vector(v: list[float]) -> str | None:
    return None if len(v) == 6 else f"must list 6 joint values in rad (got {len(v)})"


def _robot_model(v: str) -> str | None:
    """A name in the robot-model registry (cell.models: no MuJoCo imported to check it)."""
    return None if v in MODELS else f"unknown robot model {v!r} (known: {', '.join(sorted(MODELS))})"


def _check_run(run: list[str], err: Callable[[str, str], ConfigError]) -> None:
    """A `run` list: service names, each once."""
    for i, name in enumerate(run):
        if problem := _name(name):
            raise err(f"run[{i}]", problem)
    if len(set(run)) != len(run):
        raise err("run", "lists a service twice")


def _check(fn: Callable[[Any], str | None]) -> Any:
    """A field the loader checks with `fn` (a problem in words, or None); no default: the embedded
    default.toml holds every default, in one place."""
    return field(metadata={"check": fn})


_T = TypeVar("_T")


@dataclass_transform(frozen_default=True, field_specifiers=(field, _check))
def _section(cls: type[_T]) -> type[_T]:
    """A table of the config: a frozen dataclass whose fields `_check` describes (so a type checker
    reads them as fields without a default, which they are)."""
    return dataclass(frozen=True)(cls)


def parse_host_port(text: str) -> tuple[str, int]:
    """'127.0.0.1:50000' or '[::1]:50000' -> (host, port)."""
    host, sep, port = text.rpartition(":")
    if not sep or not port.isdigit():
        raise ValueError(f"must be HOST:PORT (got {text!r})")
    host = host[1:-1] if host.startswith("[") and host.endswith("]") else host
    if not host:
        raise ValueError(f"must be HOST:PORT (got {text!r})")
    if host != "localhost":
        try:
            ipaddress.ip_address(host)
        except ValueError:
            raise ValueError(f"host must be an IP address or 'localhost' (got {host!r})") from None
    if not 1 <= int(port) <= 65535:
        raise ValueError(f"port must be 1..65535 (got {port})")
    return host, int(port)


# --- the schema --------------------------------------------------------------------------------


@_section
class CellSection:
    name: str = _check(_name)
    host: str = _check(lambda v: None if v == "" else _name(v))  # this host, in a cell of [hosts]


@_section
class HostConfig:
    """One host of a cell that spans several: its address and the services it runs."""

    address: str = _check(lambda v: _host_port(f"{v}:1"))
    run: list[str]

    def validate(self, err: Callable[[str, str], ConfigError]) -> None:
        _check_run(self.run, err)


@_section
class BusConfig:
    pub: str = _check(_zmq_endpoint)
    sub: str = _check(_zmq_endpoint)
    hwm: int = _check(_positive)
    heartbeat_s: float = _check(_positive)  # ZMTP PING on every bus connection this often ...
    heartbeat_timeout_s: float = _check(_positive)  # ... and one that stays silent this long is reconnected
    connect_timeout_s: float = _check(_positive)
    request_timeout_s: float = _check(_positive)
    curve: bool  # CurveZMQ on every bus connection (cell/bus/curve.py)
    keys: str  # the directory `cell keys generate` wrote
    client: str = _check(_name)  # this host's client certificate in it
    cell: str = field(default="", metadata={"internal": True})  # [cell] name: who the bus belongs to

    def validate(self, err: Callable[[str, str], ConfigError]) -> None:
        if self.pub == self.sub:
            raise err("sub", "must differ from bus.pub")
        if self.heartbeat_timeout_s <= self.heartbeat_s:
            raise err("heartbeat_timeout_s", "must exceed bus.heartbeat_s")
        if self.curve and not self.keys:
            raise err("keys", "curve = true needs the keys directory (`cell keys generate`)")


MAIN_GROUP = "main"  # the process of every service no [[services.groups]] entry names


@_section
class GroupDefaults:
    """Keys every [[services.groups]] entry inherits unless it sets them itself."""

    cpus: list[int] = field(metadata={"check": lambda v: _cpus(v)})
    rt_priority: int = _check(lambda v: _rt_priority(v))
    nice: int = _check(lambda v: _nice(v))
    bus_pub: str
    bus_sub: str


@_section
class ProcessGroup:
    """Services that share one OS process, and how the OS schedules it (layout = "groups")."""

    name: str = _check(_name)
    services: list[str]
    cpus: list[int] = field(metadata={"check": lambda v: _cpus(v)})
    rt_priority: int = _check(lambda v: _rt_priority(v))
    nice: int = _check(lambda v: _nice(v))
    # the bus endpoints this group's services connect to instead of [bus] pub/sub ("": those): a group
    # that reaches the bus over another path (a WAN link, a delay emulator, a remote host's bus)
    bus_pub: str
    bus_sub: str

    def validate(self, err: Callable[[str, str], ConfigError]) -> None:
        if self.name == MAIN_GROUP:
            raise err("name", f"{MAIN_GROUP!r} is the process of the services no group names")
        if not self.services:
            raise err("services", "must name at least one service")
        if bool(self.bus_pub) != bool(self.bus_sub):
            raise err("bus_pub", "bus_pub and bus_sub go together (or neither)")
        if self.bus_pub and "bus" in self.services:
            raise err("bus_pub", "the bus service binds [bus] pub/sub itself: no bus override in its group")


@_section
class ServicesConfig:
    run: list[str]
    layout: Literal["groups", "single", "each"]
    on_failure: Literal["restart", "stop"]
    backoff_initial_s: float = _check(_positive)
    backoff_max_s: float = _check(_positive)
    heartbeat_s: float = _check(_positive)
    group_defaults: GroupDefaults
    groups: list[ProcessGroup]
    plugins: dict[str, str] = field(default_factory=dict)

    def validate(self, err: Callable[[str, str], ConfigError]) -> None:
        _check_run(self.run, err)
        seen: dict[str, str] = {}
        for i, g in enumerate(self.groups):
            if any(o.name == g.name for o in self.groups[:i]):
                raise err(f"groups[{i}].name", f"{g.name!r} is used by another group")
            for name in g.services:
                if name in seen:
                    raise err(f"groups[{i}].services", f"{name!r} is in group {seen[name]!r} already")
                seen[name] = g.name
        for name, entry in self.plugins.items():
            if problem := _name(name):
                raise err(f"plugins.{name}", problem)
            if not _ENTRY.fullmatch(entry):
                raise err(f"plugins.{name}", f"must be 'package.module:attribute' (got {entry!r})")
        if self.backoff_max_s < self.backoff_initial_s:
            raise err("backoff_max_s", "must be >= backoff_initial_s")


@_section
class EgressConfig:
    """The data plane's egress port (NSDI'22 Appendix C): a line rate, a buffer per queue and how
    robot commands share it with forwarded traffic.  rate_mbps = 0: no limit (the kernel's)."""

    rate_mbps: float = _check(lambda v: None if v >= 0 else f"must be >= 0 (got {v})")
    buffer_kb: float = _check(_positive)
    scheduling: Literal["fifo", "priority"]


_IFNAME = re.compile(r"[A-Za-z0-9_-]{1,13}")


def _ipv4(v: str) -> str | None:
    try:
        ipaddress.IPv4Address(v)
    except ValueError:
        return f"must be an IPv4 address (got {v!r})"
    return None


@_section
class XdpConfig:
    """The XDP backend's switch: a network namespace the launcher creates, joined to the host by a
    veth pair (<veth>0 on the host, <veth>1 in the namespace, where the program is attached)."""

    netns: str = _check(lambda v: None if _IFNAME.fullmatch(v) else f"1-13 of A-Z a-z 0-9 _ - (got {v!r})")
    veth: str = _check(lambda v: None if _IFNAME.fullmatch(v) else f"1-13 of A-Z a-z 0-9 _ - (got {v!r})")
    host_addr: str = _check(_ipv4)  # the host's end: robots bind it
    switch_addr: str = _check(_ipv4)  # the switch's end: [dataplane] listen's host
    prefix: int = _check(lambda v: None if 8 <= v <= 30 else f"must be 8..30 (got {v})")
    cpu: int = _check(lambda v: None if v >= -1 else f"must be a CPU number or -1 (got {v})")


XDP_OBJECT = Path(__file__).parent / "dataplane" / "xdp" / "dataplane.bpf.o"  # `make bpf` builds it


@functools.cache
def xdp_missing() -> str | None:
    """What keeps the XDP backend from running on this machine, or None (asked once a process)."""
    if os.geteuid() != 0 or not _capable():
        return "it needs root with CAP_NET_ADMIN and CAP_BPF (or CAP_SYS_ADMIN): the switch and the program"
    if shutil.which("ip") is None:
        return "it needs `ip` (Debian's iproute2) for the switch's namespace"
    if not XDP_OBJECT.exists():
        return f"{XDP_OBJECT} is not built: `make bpf` (needs clang and libbpf-dev)"
    try:
        ctypes.CDLL("libbpf.so.1")
    except OSError:
        return "it needs libbpf.so.1 (Debian's libbpf1)"
    return None


def _capable() -> bool:
    """Whether this process holds the capabilities XDP needs (root in a container may not)."""
    try:
        with open("/proc/self/status") as f:
            caps = next((int(line.split()[1], 16) for line in f if line.startswith("CapEff:")), 0)
    except OSError:
        return False
    net_admin, sys_admin, bpf = (caps >> bit & 1 for bit in (12, 21, 39))  # (linux/capability.h)
    return bool(net_admin and (bpf or sys_admin))


def _loopback(host: str) -> bool:
    return host == "localhost" or ipaddress.ip_address(host).is_loopback


XDP_MAX_ENTITIES = 4096  # entities the XDP program's maps hold (cell/dataplane/xdp/dataplane.bpf.c)


@_section
class ForwardRule:
    """Ordinary (non-robot) UDP traffic the data plane forwards: what arrives on `listen` goes to
    `to`, through the egress port (the paper's switch port-forwarded its background traffic)."""

    listen: str = _check(_host_port)
    to: str = _check(_host_port)


@_section
class DataplaneBackend:
    """What a [dataplane] backend is, for what depends on it (the class that runs it is in
    cell.dataplane.backends): one place, not the name compared in each."""

    name: str
    in_kernel: bool  # its packet path in the kernel (XDP): a switch namespace of its own, root, clang
    batched: bool  # Python answers a wake-up's statuses as a batch (numpy); C answers each burst
    forwards: bool  # forwarding rules and an egress model (numpy's only, yet)


DATAPLANE_BACKENDS = {
    b.name: b
    for b in (
        DataplaneBackend("numpy", in_kernel=False, batched=True, forwards=True),
        DataplaneBackend("native", in_kernel=False, batched=False, forwards=False),
        DataplaneBackend("xdp", in_kernel=True, batched=False, forwards=False),
    )
}


@_section
class DataplaneConfig:
    listen: str = _check(_host_port)
    capacity: int = _check(_positive)
    max_entities: int = _check(_positive)
    max_joints: int = _check(_positive)
    n_bits: int = _check(lambda v: None if 2 <= v <= 16 else f"must be 2..16 (got {v})")
    c1: list[float] = field(metadata={"check": _joint_vector})
    c2: list[float] = field(metadata={"check": _joint_vector})
    v_max: list[float] = field(metadata={"check": _joint_vector})
    batch: int = _check(_positive)
    egress: EgressConfig
    forward: list[ForwardRule]
    backend: Literal["auto", "numpy", "native", "xdp"]
    xdp: XdpConfig
    # the cell runs its data plane, on one host ([services] run, no [hosts]): "auto" may then put it
    # in the kernel (whoever plays the data plane else listens on `listen`, as the robots send there)
    one_host: bool = field(default=True, metadata={"internal": True})

    def chosen(self) -> tuple[str, str]:
        """The backend that runs, and why: "auto" is the XDP program in the kernel where it can run
        and the cell is on one host (listen on loopback: its robots are this host's), else the
        native data plane (C, no Python per packet) where a C compiler is installed, else numpy;
        numpy wherever forwarding rules or an egress model need it."""
        if self.backend != "auto":
            return self.backend, "set in [dataplane] backend"
        if self.forward or self.egress.rate_mbps > 0:
            return "numpy", "auto: forwarding rules or an egress model need the numpy data plane"
        if not self.one_host:
            why_not: str | None = "the cell runs no data plane of its own on this one host"
        elif not _loopback(parse_host_port(self.listen)[0]):
            why_not = "[dataplane] listen is not on loopback (robots of other hosts)"
        elif self.max_entities > XDP_MAX_ENTITIES:
            why_not = f"max_entities is over the program's {XDP_MAX_ENTITIES}"
        elif (why_not := xdp_missing()) is None:
            return "xdp", "auto: XDP can run here (root, ip, libbpf, the built program): the kernel answers"
        if not (os.environ.get("CC") or shutil.which("cc") or shutil.which("gcc") or shutil.which("clang")):
            return "numpy", "auto: no C compiler to build the native data plane (cell/dataplane/native.c)"
        return "native", f"auto: the XDP program's C in user space, no Python per packet (not XDP: {why_not})"

    @property
    def runs(self) -> DataplaneBackend:
        """The backend that runs (chosen())."""
        return DATAPLANE_BACKENDS[self.chosen()[0]]

    @property
    def switch(self) -> XdpConfig:
        """The XDP switch the in-kernel backend runs behind: [dataplane.xdp] as written with
        backend = "xdp"; with "auto", a switch of its own per listen port, so that two cells run at
        once (namespace cellsw<port>, veth csw<port>0/1, a /30 of host_addr's /16)."""
        if self.backend == "xdp":
            return self.xdp
        port = parse_host_port(self.listen)[1]
        base = int(ipaddress.IPv4Network(f"{self.xdp.host_addr}/16", strict=False).network_address)
        base += 4 * (port % 16384)
        return replace(
            self.xdp,
            netns=f"cellsw{port}",
            veth=f"csw{port}",
            host_addr=str(ipaddress.IPv4Address(base + 1)),
            switch_addr=str(ipaddress.IPv4Address(base + 2)),
            prefix=30,
        )

    @property
    def address(self) -> str:
        """Where the data plane takes statuses ("HOST:PORT"): [dataplane] listen, or for the
        in-kernel backend listen's port on the switch's end of its veth pair."""
        if not self.runs.in_kernel:
            return self.listen
        return f"{self.switch.switch_addr}:{parse_host_port(self.listen)[1]}"

    @property
    def sender_host(self) -> str:
        """The address a sender on this host binds to reach `address` (a probe, a test's robot): the
        host's end of the switch's veth pair for the in-kernel backend, else loopback."""
        return self.switch.host_addr if self.runs.in_kernel else "127.0.0.1"

    def validate(self, err: Callable[[str, str], ConfigError]) -> None:
        runs = self.runs
        if runs.in_kernel and self.backend == "xdp":  # ("auto" places its switch itself: switch)
            x = self.xdp
            host = parse_host_port(self.listen)[0]
            if host != x.switch_addr:
                why = f'with backend = "xdp" it must be on [dataplane.xdp] switch_addr ({x.switch_addr})'
                raise err("listen", why)
            net = ipaddress.IPv4Network(f"{x.host_addr}/{x.prefix}", strict=False)
            if x.host_addr == x.switch_addr or ipaddress.IPv4Address(x.switch_addr) not in net:
                why = f"must be another address in {net} (the host's end is {x.host_addr})"
                raise err("xdp.switch_addr", why)
        if self.backend != "auto" and not runs.forwards:  # ("auto" picks numpy for these)
            if self.forward or self.egress.rate_mbps > 0:
                why = f"the {self.backend} backend has no forwarding rules or egress model yet (numpy has)"
                raise err("backend", why)
            if self.max_entities > XDP_MAX_ENTITIES:
                why = f"the XDP program holds {XDP_MAX_ENTITIES} (dataplane.bpf.c's MAX_ENTITIES; native too)"
                raise err("max_entities", why)
        for i, f in enumerate(self.forward):
            if f.listen == self.listen or any(o.listen == f.listen for o in self.forward[:i]):
                raise err(f"forward[{i}].listen", f"{f.listen} is taken by the data plane or another rule")
        for i, v in enumerate(self.v_max):
            if not 0 < v <= 10:
                raise err(f"v_max[{i}]", f"must be in (0, 10] rad/s (got {v})")


@_section
class ControllerConfig:
    tp_rate_hz: float = _check(lambda v: None if 1 <= v <= 500 else f"must be 1..500 TP/s (got {v})")
    fine_rate_hz: float = _check(lambda v: None if 1 <= v <= 500 else f"must be 1..500 TP/s (got {v})")
    # a followed trajectory's TPs are fitted so the modelled tool stays this close to its plan (mm)
    follow_tolerance_mm: float = _check(
        lambda v: None if 0.001 <= v <= 100 else f"must be 0.001..100 mm (got {v})"
    )
    episode: int = _check(lambda v: None if v >= 2 else f"must be >= 2 TPs (got {v})")
    lead_s: float = _check(_positive)
    a_max: list[float] = field(metadata={"check": _joint_vector})
    j_max: list[float] = field(metadata={"check": _joint_vector})
    tool_v_max: float = _check(_positive)
    tool_a_max: float = _check(_positive)
    tool_j_max: float = _check(_positive)
    tool_w_max: float = _check(_positive)
    # a motion is answered done only after the robot's status, read after its plan ended, has every
    # joint within goal_tolerance_rad of the end (and still: |v| within 10x that per second), at most
    # settle_s after the plan's end; else it failed (NotAtGoal), saying where the robot stands
    goal_tolerance_rad: float = _check(_positive)
    settle_s: float = _check(_positive)
    # where named trajectories are kept across restarts ("": cell.trajectory.named.state_dir's default)
    state_dir: str


@_section
class SkillsConfig:
    host: str = _check(lambda v: _host_port(f"{v}:1"))
    break_tolerance_rad: float = _check(_positive)
    motion_timeout_s: float = _check(_positive)
    # what one peer can take of a skill server (refusals are counted, and said in an error reply)
    max_connections: int = _check(_positive)  # connections per skill server, all peers together
    max_connections_per_peer: int = _check(_positive)  # of those, from one IP address
    max_pending: int = _check(_positive)  # commands of one connection not yet answered: reading pauses
    line_timeout_s: float = _check(_positive)  # a started command message must end within this


@_section
class RecorderConfig:
    mode: Literal["off", "save", "serve", "spawn"]
    path: str
    hz: float = _check(lambda v: None if 0 < v <= 500 else f"must be in (0, 500] (got {v})")
    series_batch_s: float = _check(lambda v: None if 0 < v <= 10 else f"must be in (0, 10] s (got {v})")
    bag: str  # a rosbag2 directory (MCAP) the run is written to as well ("": none; cell.recorder.bag)


@_section
class SnpConfig:
    listen: str = _check(_host_port)


def _vector3(v: Any) -> str | None:
    if not isinstance(v, list) or len(v) != 3 or not all(isinstance(x, int | float) for x in v):
        return f"must be a list of 3 numbers (got {v!r})"
    return None


@_section
class VisionConfig:
    """The simulated close-range camera (service `vision`) and its frame buffer."""

    robot: str = _check(lambda v: None if v == "" else _name(v))  # "": the cell's first robot
    fps: float = _check(lambda v: None if 0 < v <= 120 else f"must be in (0, 120] (got {v})")
    buffer: int = _check(lambda v: None if 1 <= v <= 1000 else f"must be 1..1000 (got {v})")
    width_px: int = _check(lambda v: None if 64 <= v <= 4096 else f"must be 64..4096 (got {v})")
    height_px: int = _check(lambda v: None if 48 <= v <= 4096 else f"must be 48..4096 (got {v})")
    position_m: list[float] = field(metadata={"check": _vector3})
    axis: list[float] = field(metadata={"check": _vector3})
    focal_mm: float = _check(_positive)
    f_number: float = _check(_positive)
    focus_mm: float = _check(_positive)
    pixel_um: float = _check(_positive)
    noise_dn: float = _check(lambda v: None if v >= 0 else f"must be >= 0 (got {v})")
    rerun_every: int = _check(lambda v: None if v >= 0 else f"must be >= 0 (got {v})")

    def validate(self, err: Callable[[str, str], ConfigError]) -> None:
        if self.focus_mm <= self.focal_mm:
            raise err("focus_mm", "must be farther than the focal length")
        if not any(self.axis):
            raise err("axis", "must not be the zero vector")


def _where(v: Any) -> str | None:
    if not isinstance(v, list) or len(v) != 6 or not all(w in ("master", "neighbour", "local") for w in v):
        return f'must list 6 of "master", "neighbour", "local", one per module (got {v!r})'
    return None


@_section
class ModularConfig:
    """The modular robot (service `modular`, seed 002): six joint modules under VDC (docs/modular.md)."""

    q0: list[float] = field(metadata={"check": _joint_vector})
    where: list[str] = field(metadata={"check": _where})  # who computes each module's [C, D]
    loss: float = _check(lambda v: None if 0 <= v <= 0.5 else f"must be in [0, 0.5] (got {v})")
    adapt: float = _check(lambda v: None if v >= 0 else f"must be >= 0 (got {v})")  # VDC's adaptation gain
    # how the four messages cross: "snp" as SnP-MrT packets between UDP sockets on loopback (the
    # master's and each module's, cell.modular.wire), "memory" handed over as they are, "cycle" the
    # SnP cycle itself: its master and modules in processes of their own (cell.modular.processes)
    transport: Literal["snp", "memory", "cycle"]
    # "cycle"'s datagrams: straight between the nodes' sockets, or through the two routers of
    # cell.snp.routed (every packet routed by path address, its return address naming its sender)
    network: Literal["direct", "routed"]
    speed_rad_s: float = _check(_positive)  # joint moves' default peak speed
    suspect_cycles: int = _check(_positive)
    lost_cycles: int = _check(_positive)
    publish_hz: float = _check(lambda v: None if 0 < v <= 500 else f"must be in (0, 500] (got {v})")

    def validate(self, err: Callable[[str, str], ConfigError]) -> None:
        if self.network == "routed" and self.transport != "cycle":
            raise err("network", 'the routers carry transport "cycle" (the SnP cycle\'s own processes)')
        chain = self.where[self.where.index("neighbour") :] if "neighbour" in self.where else []
        if self.transport == "cycle" and any(w != "neighbour" for w in chain):
            raise err(
                "where",
                'on transport "cycle" the modules whose [C, D] is by "neighbour" must run out to the tip '
                "(each takes its outboard neighbour's force, the tip none)",
            )


@_section
class RlinkConfig:
    """The cell's Responsive Link: where its nodes listen, their addresses, the beacon."""

    host: str = _check(lambda v: _host_port(f"{v}:1"))
    port: int = _check(lambda v: None if 1 <= v <= 65535 - 8 else f"must be 1..{65535 - 8} (got {v})")
    hub: int = _check(lambda v: None if 1 <= v <= 254 else f"must be 1..254 (got {v})")
    dataplane: int = _check(lambda v: None if 1 <= v <= 254 else f"must be 1..254 (got {v})")
    robots: int = _check(lambda v: None if 1 <= v <= 254 else f"must be 1..254 (got {v})")
    beacon_hz: float = _check(lambda v: None if 0 <= v <= 1000 else f"must be 0..1000 (got {v})")
    watchdog_s: float = _check(lambda v: None if v >= 0 else f"must be >= 0 (got {v})")
    stop_decel: float = _check(lambda v: None if 0 < v <= 1 else f"must be in (0, 1] (got {v})")

    def validate(self, err: Callable[[str, str], ConfigError]) -> None:
        if len({self.hub, self.dataplane, self.robots}) != 3:
            raise err("hub", "the hub, dataplane and robots nodes need addresses of their own")
        if self.watchdog_s and self.beacon_hz and self.watchdog_s * self.beacon_hz < 2:
            raise err("watchdog_s", "must cover at least two beacon periods (or be 0: off)")


@_section
class RobotConfig:
    id: int = _check(lambda v: None if 1 <= v <= 0xFFFF else f"must be 1..65535 (got {v})")
    name: str = _check(_name)
    model: str = _check(_robot_model)  # a name of cell.models' registry
    # "ur": not emulated here: a UR controller at ur_address, brought in by the daemon (cell.ur.remote)
    backend: Literal["mujoco", "kinematic", "ur"]
    skill_port: int = _check(_port)
    status_hz: int = _check(_positive)
    command_hz: int = _check(_positive)
    truth_hz: float = _check(lambda v: None if v >= 0 else f"must be >= 0 (got {v})")
    watchdog_windows: int = _check(_positive)
    q0: list[float]  # one per joint of the model (RobotConfig.validate)
    host: str = _check(lambda v: None if v == "" else _name(v))  # the host emulating it ("": the only one)
    # the address its UR controller interfaces (RTDE, dashboard, ...) listen on ("": 127.0.1.<id>); with
    # backend "ur", that of the UR controller the daemon connects to
    ur_address: str = _check(lambda v: None if v == "" else _host_port(f"{v}:1"))
    # backend "ur" only: emulate that controller here ("mujoco" or "kinematic"), an arm that offers only
    # its UR interfaces, as URSim or a real UR5e does ("": a real controller at ur_address)
    ur_emulate: Literal["", "mujoco", "kinematic"]
    # "own": a UDP socket (address and port) of its own, as a real arm has; "shared": one socket for its
    # whole group (robots of one backend, model and rates), all its statuses in one GSO send a tick and
    # the data plane's answers to them in a few: fleets of hundreds of arms in one process
    socket: Literal["own", "shared"]
    # "native": the group's tick in C (cell/robot/tick.c), no Python per tick; "python": the reference
    # model it is held to (and the fallback where no C compiler works)
    tick: Literal["native", "python"]
    # what its joints' names start with in a trajectory naming several robots' joints (a dual-arm
    # MoveIt group): "" is its name and "_" (r1_shoulder_pan_joint)
    joint_prefix: str = _check(
        lambda v: None if v == "" or v.strip() == v else f"no spaces around it (got {v!r})"
    )

    @property
    def ur_host(self) -> str:
        """Its UR interfaces' address: ur_address, else its own loopback one (r1 127.0.1.1)."""
        return self.ur_address or f"127.0.{1 + self.id // 256}.{self.id % 256}"

    @property
    def prefix(self) -> str:
        """Its joints' prefix in a trajectory of several robots (joint_prefix, else `<name>_`)."""
        return self.joint_prefix or f"{self.name}_"

    def validate(self, err: Callable[[str, str], ConfigError]) -> None:
        if len(self.q0) != (joints := get(self.model).joints):
            raise err("q0", f"must list {joints} joint values in rad, one per joint of a {self.model}")
        if self.command_hz > self.status_hz:
            raise err("command_hz", f"must be <= status_hz ({self.status_hz})")
        if self.status_hz % self.command_hz:
            raise err("command_hz", f"must divide status_hz ({self.status_hz}): windows end on status ticks")
        if self.truth_hz > self.status_hz:
            raise err("truth_hz", f"must be <= status_hz ({self.status_hz})")
        if self.backend == "ur":
            if not (self.ur_address or self.ur_emulate):
                raise err("ur_address", "with backend = 'ur': the UR controller's address (or ur_emulate)")
            if 500 % self.status_hz:
                raise err("status_hz", "with backend = 'ur': must divide the UR controller's 500 Hz")
        elif self.ur_emulate:
            raise err("ur_emulate", f'only for backend = "ur" (this robot is backend = "{self.backend}")')


@_section
class RobotDefaults:
    """Keys every [[robots]] entry inherits unless it sets them itself."""

    model: str = _check(_robot_model)
    backend: Literal["mujoco", "kinematic", "ur"]
    status_hz: int = _check(_positive)
    command_hz: int = _check(_positive)
    truth_hz: float = _check(lambda v: None if v >= 0 else f"must be >= 0 (got {v})")
    watchdog_windows: int = _check(_positive)
    q0: list[float]  # one per joint of the model (RobotConfig.validate)
    host: str = _check(lambda v: None if v == "" else _name(v))
    ur_address: str = _check(lambda v: None if v == "" else _host_port(f"{v}:1"))
    ur_emulate: Literal["", "mujoco", "kinematic"]
    socket: Literal["own", "shared"]
    tick: Literal["native", "python"]
    joint_prefix: str = _check(
        lambda v: None if v == "" else f"a robot's own (got {v!r}): set it in its [[robots]] entry"
    )


@_section
class URConfig:
    """The UR controller's interfaces each emulated arm offers (cell.ur)."""

    interfaces: bool  # offer them at all
    rtde_port: int = _check(_port)
    dashboard_port: int = _check(_port)
    primary_port: int = _check(_port)  # URScript in, messages out
    secondary_port: int = _check(_port)
    realtime_port: int = _check(_port)  # URScript in (ur_rtde sends its control script here)
    max_clients: int = _check(_positive)  # connections per arm and interface; more are refused
    programs: str  # the programs folder ("": the cell's own; cell.ur.programs)
    remote_control: bool  # what `is in remote control` answers (URSim's: false; nothing refused either way)
    # the daemon (robots of backend "ur"): the first of the registers its script uses (input int: the
    # window's number; input doubles, six: the joint velocities; output ints: the number echoed, a
    # heartbeat).  24-47 are the range UR leaves to external RTDE clients (0-23 serve the fieldbuses)
    daemon_registers: int = _check(lambda v: None if 0 <= v <= 42 else f"must be 0..42 (got {v})")
    daemon_restart_s: float = _check(lambda v: None if 0 < v <= 60 else f"must be in (0, 60] (got {v})")


# the key of the address each of these services binds: it must run on the host with that address
_BINDS = {
    "bus": "bus.pub",
    "dataplane": "dataplane.listen",
    "snp": "snp.listen",
    "skills": "skills.host",
    "rlink": "rlink.host",
}


def _bound_host(config: CellConfig, service: str) -> str:
    """The address `service` binds ("": nothing to check, as for an ipc:// bus)."""
    if service == "bus":
        return parse_host_port(config.bus.pub[6:])[0] if config.bus.pub.startswith("tcp://") else ""
    if service in ("dataplane", "snp"):
        return parse_host_port(getattr(config, service).listen)[0]
    return str(getattr(config, service).host)


@_section
class CellConfig:
    cell: CellSection
    bus: BusConfig
    services: ServicesConfig
    dataplane: DataplaneConfig
    controller: ControllerConfig
    skills: SkillsConfig
    recorder: RecorderConfig
    snp: SnpConfig
    rlink: RlinkConfig
    vision: VisionConfig
    modular: ModularConfig
    ur: URConfig
    robot_defaults: RobotDefaults
    robots: list[RobotConfig]
    hosts: dict[str, HostConfig]
    source: str = field(default=DEFAULT_SOURCE, metadata={"internal": True})

    def validate(self, err: Callable[[str, str], ConfigError]) -> None:
        for attr in ("id", "name", "skill_port"):
            seen: set[object] = set()
            for i, robot in enumerate(self.robots):
                value = getattr(robot, attr)
                if value in seen:
                    raise err(f"robots[{i}].{attr}", f"{value!r} is used by another robot")
                seen.add(value)
        names = {r.name for r in self.robots}
        if "vision" in self.services.run and self.vision.robot and self.vision.robot not in names:
            raise err("vision.robot", f"{self.vision.robot!r} is not a robot of this cell")
        self._validate_hosts(err)

    def _validate_hosts(self, err: Callable[[str, str], ConfigError]) -> None:
        """A cell of several hosts: every robot on one of them, every bound address on the host that
        runs the service binding it (a robot on host b sending to 127.0.0.1 would reach nobody)."""
        for name in self.hosts:
            if problem := _name(name):
                raise err(f"hosts.{name}", problem)
        if not self.hosts:
            if self.cell.host:
                raise err("cell.host", f"{self.cell.host!r} is not one of [hosts] (there are none)")
            for i, r in enumerate(self.robots):
                if r.host:
                    raise err(f"robots[{i}].host", f"{r.host!r}: this cell has no [hosts]")
            return
        known = ", ".join(sorted(self.hosts))
        if self.cell.host not in self.hosts:
            what = f"{self.cell.host!r} is not one of" if self.cell.host else "must name this host, one of"
            raise err("cell.host", f"{what} {known} (`--host NAME`)")
        for i, r in enumerate(self.robots):
            if r.host not in self.hosts:
                raise err(f"robots[{i}].host", f"must name the host emulating {r.name}, one of {known}")
            if "robots" not in self.hosts[r.host].run:
                raise err(f"robots[{i}].host", f"host {r.host!r} does not run service 'robots'")
        owner: dict[str, str] = {}
        for host, h in self.hosts.items():
            for svc in h.run:
                if svc in _BINDS:
                    if svc in owner:
                        raise err(f"hosts.{host}.run", f"{svc!r} runs on host {owner[svc]!r} already")
                    owner[svc] = host
                    bound = _bound_host(self, svc)
                    if bound and bound not in (h.address, "0.0.0.0", "::"):
                        raise err(
                            _BINDS[svc],
                            f"{svc!r} runs on host {host!r}: it must bind that host's address {h.address} "
                            f"(got {bound})",
                        )

        if owner.get("dataplane", owner.get("rlink")) != owner.get("rlink", owner.get("dataplane")):
            raise err(
                "hosts",
                "dataplane and rlink must run on one host (the data plane's link node binds [rlink] host)",
            )

    def runs(self, service: str) -> bool:
        """Whether the cell runs `service`: on this host, or on any of its [hosts]."""
        return service in self.services.run or any(service in h.run for h in self.hosts.values())

    def here(self) -> HostConfig | None:
        """This host, in a cell of several (None: the cell has one)."""
        return self.hosts.get(self.cell.host)

    def local_robots(self) -> list[RobotConfig]:
        """The robots this host emulates."""
        return [r for r in self.robots if r.host == self.cell.host]

    def rlink_robots(self) -> list[RobotConfig]:
        """The robots on the host of the Responsive Link's hub: their node halts them and reports
        them still (robots of other hosts stop on the data plane's stop ramp, unreported)."""
        if not self.hosts:
            return list(self.robots)
        hub = next((h for h, c in self.hosts.items() if "rlink" in c.run), None)
        return [r for r in self.robots if r.host == hub]

    def robot(self, name: str) -> RobotConfig:
        robot = self._robot_named.get(name)
        if robot is None:
            raise KeyError(f"no robot named {name!r} in {self.source}")
        return robot

    @functools.cached_property
    def _robot_named(self) -> dict[str, RobotConfig]:
        """The robots by name (a controller looks a fleet's robots up by name on every motion)."""
        return {r.name: r for r in reversed(self.robots)}  # (the first of a name, as a scan finds it)

    def to_dict(self) -> dict[str, Any]:
        data = asdict(self)
        del data["source"]
        del data["bus"]["cell"]  # (internal: [cell] name, as the bus knows it)
        del data["dataplane"]["one_host"]  # (internal: from [services] and [hosts])
        return data

    def to_toml(self) -> str:
        return tomli_w.dumps(self.to_dict())


# --- loading -----------------------------------------------------------------------------------


def default_text() -> str:
    return resources.files("cell").joinpath("default.toml").read_text()


@functools.cache
def _default_data() -> dict[str, Any]:
    return tomllib.loads(default_text())


_hints = functools.cache(get_type_hints)  # (evaluating a dataclass's hints is most of a config's load)


def load_config(path: str | Path | None = None, overrides: dict[str, Any] | None = None) -> CellConfig:
    """The effective config: `path` (if any) merged over the embedded default, then `overrides`."""
    if path is None:
        return config_from_text("", DEFAULT_SOURCE, overrides)
    try:
        text = Path(path).read_text()
    except (OSError, UnicodeDecodeError) as exc:
        why = exc.strerror if isinstance(exc, OSError) else f"not UTF-8 text ({exc.reason})"
        raise ConfigError(str(path), "", f"cannot read: {why}") from None
    return config_from_text(text, str(path), overrides)


def config_from_text(text: str, source: str, overrides: dict[str, Any] | None = None) -> CellConfig:
    """The effective config of a config file's text merged over the embedded default."""
    data = copy.deepcopy(_default_data())
    if text:
        try:
            user = tomllib.loads(text)
        except tomllib.TOMLDecodeError as exc:
            raise ConfigError(source, "", f"not valid TOML: {exc}") from None
        data = _merge(data, user)
    if overrides:
        data = _merge(data, overrides)
    return config_from_dict(_listen_follows_backend(data), source)


def _listen_follows_backend(data: dict[str, Any]) -> dict[str, Any]:
    """[dataplane] backend = "xdp" alone moves the data plane's listen address (left at its
    default) onto the switch's end of the veth pair, keeping its port: the only address it can have."""
    dp, default = data.get("dataplane"), _default_data()["dataplane"]
    if not isinstance(dp, dict) or dp.get("backend") != "xdp" or dp.get("listen") != default["listen"]:
        return data
    switch = dp.get("xdp", {}).get("switch_addr") if isinstance(dp.get("xdp"), dict) else None
    if not isinstance(switch, str):
        return data
    port = parse_host_port(default["listen"])[1]
    return {**data, "dataplane": {**dp, "listen": f"{switch}:{port}"}}


def config_from_dict(data: dict[str, Any], source: str = DEFAULT_SOURCE) -> CellConfig:
    data = _with_defaults(data, "robots", data.get("robot_defaults"))
    services = data.get("services")
    if isinstance(services, dict):
        data = {**data, "services": _with_defaults(services, "groups", services.get("group_defaults"))}
    config = replace(_build(CellConfig, data, "", source), source=source)
    config = replace(config, bus=replace(config.bus, cell=config.cell.name))
    one_host = "dataplane" in config.services.run and not config.hosts
    config = replace(config, dataplane=replace(config.dataplane, one_host=one_host))
    here = config.here()
    if here is not None:  # a host of several: it runs its own services, with its own bus certificate
        services = replace(config.services, run=list(here.run))
        config = replace(config, services=services, bus=replace(config.bus, client=config.cell.host))
    return config


def _with_defaults(table: dict[str, Any], key: str, defaults: Any) -> dict[str, Any]:
    """table[key] (an array of tables) with each entry's missing keys taken from defaults."""
    entries = table.get(key)
    if not isinstance(entries, list) or not isinstance(defaults, dict):
        return table
    return {**table, key: [{**defaults, **e} if isinstance(e, dict) else e for e in entries]}


def _merge(base: dict[str, Any], over: dict[str, Any]) -> dict[str, Any]:
    out = dict(base)
    for key, value in over.items():
        if isinstance(value, dict) and isinstance(out.get(key), dict):
            out[key] = _merge(out[key], value)
        else:
            out[key] = value
    return out


def _join(path: str, key: str) -> str:
    return f"{path}.{key}" if path else key


def _build(cls: type, data: Any, path: str, source: str) -> Any:
    if not isinstance(data, dict):
        raise ConfigError(source, path, f"must be a table (got {_kind(data)})")
    hints = _hints(cls)
    known = {f.name: f for f in fields(cls) if not f.metadata.get("internal")}
    for key in data:
        if key not in known:
            raise ConfigError(source, _join(path, key), f"unknown key (known: {', '.join(sorted(known))})")
    kwargs = {}
    for name, f in known.items():
        key = _join(path, name)
        if name not in data:
            raise ConfigError(source, key, "missing")
        value = _convert(hints[name], data[name], key, source)
        if (check := f.metadata.get("check")) and (problem := check(value)):
            raise ConfigError(source, key, problem)
        kwargs[name] = value
    obj = cls(**kwargs)
    if hasattr(obj, "validate"):
        obj.validate(lambda sub, problem: ConfigError(source, _join(path, sub), problem))
    return obj


def _kind(value: Any) -> str:
    return {dict: "a table", list: "an array", str: "a string", bool: "a boolean"}.get(
        type(value), type(value).__name__
    )


def _convert(tp: Any, value: Any, key: str, source: str) -> Any:
    origin = get_origin(tp)
    if isinstance(tp, type) and is_dataclass(tp):
        return _build(tp, value, key, source)
    if origin is Literal:
        choices = get_args(tp)
        if value not in choices:
            raise ConfigError(source, key, f"must be one of {', '.join(map(repr, choices))} (got {value!r})")
        return value
    if origin is list:
        if not isinstance(value, list):
            raise ConfigError(source, key, f"must be an array (got {_kind(value)})")
        (item,) = get_args(tp)
        return [_convert(item, v, f"{key}[{i}]", source) for i, v in enumerate(value)]
    if origin is dict:
        if not isinstance(value, dict):
            raise ConfigError(source, key, f"must be a table (got {_kind(value)})")
        _, item = get_args(tp)
        return {k: _convert(item, v, _join(key, k), source) for k, v in value.items()}
    if origin in (Union, types.UnionType):
        raise TypeError(f"unions are not supported in the config schema ({key})")
    if tp is bool:
        if not isinstance(value, bool):
            raise ConfigError(source, key, f"must be true or false (got {value!r})")
        return value
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(source, key, f"must be an integer (got {value!r})")
        return value
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise ConfigError(source, key, f"must be a number (got {value!r})")
        return float(value)
    if tp is str:
        if not isinstance(value, str):
            raise ConfigError(source, key, f"must be a string (got {value!r})")
        return value
    raise TypeError(f"unsupported config type {tp!r} at {key}")
