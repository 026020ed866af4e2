"""Hypothesis strategies for every input the cell takes from a peer, built with the codecs' own encoders.

They are the seeds `cell fuzz` mutates (well-formed inputs reach the deep
paths a random byte string never does) and the inputs of the property tests.
`examples()` draws a reproducible list from any of them.
"""

from __future__ import annotations

from typing import Any

import tomli_w
from hypothesis import HealthCheck, Phase, given, seed, settings
from hypothesis import strategies as st

from cell.bus.envelope import Encoder
from cell.bus.envelope import Kind as BusKind
from cell.rlink import packet as rlp
from cell.robot.datagram import SCALE, Datagram, Kind
from cell.robot.datagram import encode as encode_datagram
from cell.skills.protocol import NAMED_SKILLS, SKILLS, Command
from cell.snp import packet as snp

u8, u16, u32, u64 = (st.integers(0, 2**b - 1) for b in (8, 16, 32, 64))
_LIMIT = (2**31 - 1) / SCALE  # the largest |value| a datagram field holds

# --- skill command lines ----------------------------------------------------------------------------

_ID_CHARS = "abcdef0123456789ABCXYZ_-"
skill_ids = st.text(_ID_CHARS, min_size=8, max_size=8) | st.text(max_size=10)
skill_names = st.sampled_from([*SKILLS, *NAMED_SKILLS, "move", "Move_To", "", "break!"])
skill_numbers = st.floats(allow_nan=True, allow_infinity=True) | st.integers(-(10**30), 10**30).map(float)
skill_commands = st.builds(
    Command,
    id=skill_ids,
    skill=skill_names,
    args=st.lists(skill_numbers, max_size=8).map(tuple),
    names=st.lists(st.text("r12al._-", max_size=8), max_size=3).map(tuple),
)


skill_lines = skill_commands.map(Command.encode)

# --- robot datagrams ------------------------------------------------------------------------------

datagrams = st.builds(
    Datagram,
    robot_id=u16,
    joint_id=u8,
    kind=st.sampled_from(list(Kind)),
    seq=u32,
    velocity=st.floats(-_LIMIT, _LIMIT),
    position=st.floats(-_LIMIT, _LIMIT),
).map(encode_datagram)

# --- SnP packets ----------------------------------------------------------------------------------

snp_headers = st.builds(
    snp.Header,
    destination=u8,
    pid=st.sampled_from([*snp.Pid, 0, 0xEE]),
    return_address=st.binary(max_size=6),
    source_process=u32,
    destination_process=u32,
)
_items = st.lists(st.builds(snp.Item, id=u32, value=st.floats(width=32), timestamp=u64), max_size=4)
_wanted = st.lists(st.builds(snp.Wanted, id=u32, timestamp=u64), max_size=4)
snp_bodies = st.one_of(
    st.builds(snp.Query, query_id=u32, deadline=u64, inputs=_items.map(tuple), outputs=_wanted.map(tuple)),
    st.builds(snp.Reply, query_id=u32, items=_items.map(tuple)),
    st.builds(snp.Denied, query_id=u32, explanation=u16),
    st.builds(snp.Cancel, query_id=u32),
    st.builds(snp.TimeRequest, t1=u64),
    st.builds(snp.TimeResponse, t1=u64, t2=u64, t3=u64),
    st.builds(snp.PidQuery, pid=u8),
    st.builds(snp.NodeInfoQuery),
    st.builds(
        snp.NodeInfo, module_id=u32, kind=u8, plugged_to=u32, port=u8,
        items=st.lists(u32, max_size=6).map(tuple), joint=u8,
    ),
    st.builds(
        snp.Configure, joint=u8, period_ns=u32, phase_ns=u32, budget_ns=u32,
        params=st.lists(st.floats(width=32), max_size=4).map(tuple),
    ),
    st.builds(snp.Configured, joint=u8, status=u8),
    st.builds(snp.TimeSubscribe, period_ns=u32, precision_ns=u32),
    st.builds(snp.TimeSubscribed, period_ns=u32, precision_ns=u32),
    st.builds(snp.TimeBeacon, seq=u32, t_master=u64),
)  # fmt: skip
snp_packets = st.builds(
    lambda h, b, t: snp.encode(h, b, t), snp_headers, snp_bodies, st.none() | st.integers(0, 0x30)
)

# --- Responsive Link packets ----------------------------------------------------------------------


@st.composite
def _rlink_packets(draw: Any) -> bytes:
    kind = draw(st.sampled_from(list(rlp.Kind)))
    p = rlp.Packet(
        kind,
        draw(u8),
        draw(u8),
        draw(st.integers(0, rlp.PRIORITIES - 1)),
        draw(st.integers(0, rlp.TYPES - 1)),
        draw(u8),
        draw(st.binary(max_size=rlp.PAYLOAD[kind])),
        draw(u8),
    )
    return rlp.encode(p)


rlink_packets = _rlink_packets()


# --- bus frames -----------------------------------------------------------------------------------

BUS_TOPICS = (
    "rpc/dataplane/state",
    "rpc/cell/status",
    "rpc/controller/pose",
    "rpc/vision/info",
    "rpc/dataplane/update",
    "rpc/robot/r1/silence",
    "rpc/controller/move",
    "rpc/dataplane/nope",
    "health/fuzz",
    "truth/r1",
    "plan/r1",
    "announce/robot/r1",
    "events/robot/r1",
    "events/service/controller",
    "nobody/listens",
)
BUS_TYPES = (
    "cell.v1.StateRequest",
    "cell.v1.StatusRequest",
    "cell.v1.RobotRequest",
    "cell.v1.Heartbeat",
    "cell.v1.RobotTruth",
    "cell.v1.TableUpdate",
    "cell.v1.Nope",
    "",
)


@st.composite
def _bus_frames(draw: Any) -> bytes:
    enc = Encoder(draw(st.text("abcxyz-", min_size=1, max_size=12)), instance=draw(u32))
    return enc.encode(
        draw(st.sampled_from(BUS_TOPICS)).encode(),
        draw(st.sampled_from(BUS_TYPES)),
        draw(st.binary(max_size=64)),
        draw(st.sampled_from(list(BusKind))),
        draw(u64),
    )


bus_frames = _bus_frames()


# --- config files ---------------------------------------------------------------------------------

_toml_values = st.recursive(
    st.none().map(lambda _: "")
    | st.booleans()
    | st.integers(-(2**63), 2**63 - 1)
    | st.floats(allow_nan=True)
    | st.text(max_size=12),
    lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=8), inner, max_size=3),
    max_leaves=6,
)


def config_texts(sections: dict[str, list[str]]) -> st.SearchStrategy[str]:
    """A user config file: known sections and keys (and a few unknown) given odd values."""
    section = st.sampled_from([*sections, "nope"])

    @st.composite
    def text(draw: Any) -> str:
        doc: dict[str, Any] = {}
        for name in draw(st.lists(section, min_size=1, max_size=3, unique=True)):
            keys = [*sections.get(name, ["x"]), "unknown_key"]
            doc[name] = {k: draw(_toml_values) for k in draw(st.lists(st.sampled_from(keys), max_size=3))}
        return tomli_w.dumps(doc)

    return text()


def examples(strategy: st.SearchStrategy[Any], n: int, seed_: int = 0) -> list[Any]:
    """n examples of a strategy, the same ones for the same seed."""
    out: list[Any] = []

    @seed(seed_)
    @settings(
        max_examples=n,
        database=None,
        deadline=None,
        phases=[Phase.generate],
        suppress_health_check=list(HealthCheck),
    )
    @given(strategy)
    def collect(x: Any) -> None:
        out.append(x)

    collect()
    return out
