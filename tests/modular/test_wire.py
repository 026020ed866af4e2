"""VDC's four messages as SnP-MrT packets (cell.modular.wire): byte layout, 32-bit values, and the arm
tracking with every message carried between real UDP sockets, junk on the way counted and guessed."""

from __future__ import annotations

import numpy as np
import pytest

from cell.modular.loop import Faults, track_vdc
from cell.modular.reference import circle
from cell.modular.vdc import A, B, C, D
from cell.modular.wire import A_QUERY, B_REPLY, C_QUERY, D_REPLY, SnpLink, b_of, b_values
from cell.snp.packet import Pid, Query, Reply, decode


@pytest.fixture
def link():
    link = SnpLink()
    yield link
    link.close()


def test_each_message_is_a_time_bounded_query_or_its_reply_with_32_bit_values(link) -> None:
    # a query: 31 bytes of header, id, deadline and input count, 16 an input (id u32, value f32,
    # timestamp u64), the output count, 12 an output (id, timestamp), the data CRC; a reply: 23, 16 an
    # item, the CRC
    assert (A_QUERY.size, B_REPLY.size) == (31 + 2 * 16 + 4 + 20 * 12 + 1, 23 + 20 * 16 + 1) == (308, 344)
    assert (C_QUERY.size, D_REPLY.size) == (31 + 6 * 16 + 4 + 12 + 1, 23 + 16 + 1) == (144, 40)
    b = B(0.5, -1.25, np.arange(6) * 0.1, np.arange(6) * -0.2, np.arange(6) * 0.3)
    link.new_cycle()
    assert link.a(2, A(1.0, 0.25)) == A(1.0, 0.25)
    got = link.b(2, b)
    assert got is not None and np.allclose(b_values(got), b_values(b), rtol=1e-7, atol=1e-7)
    assert b_values(got) != b_values(b)  # (0.1 etc. are not 32-bit floats: the wire rounds them)
    f = np.array([1.5, -2.0, 3.25, 100.0, -200.5, 9.8125])
    c = link.c(2, C(f))
    assert c is not None and np.array_equal(c.f_star, f)  # (all exact in 32 bits)
    assert link.d(2, D(-12.5)) == D(-12.5)
    # the codec the cycle's fast path packs is the generic SnP-MrT one, item ids and all
    module_sock, master_sock = link.modules[0], link.master
    module_sock.sendto(A_QUERY.pack(0, Pid.MRT, 1, 0, 7, 99, (257, 0.5, 1, 513, 0.25, 1), (1, 2) * 20),
                       master_sock.getsockname())  # fmt: skip
    pkt = decode(master_sock.recv(2048))
    assert isinstance(pkt.body, Query) and pkt.body.query_id == 7 and len(pkt.body.outputs) == 20
    assert [(i.id, i.value) for i in pkt.body.inputs] == [(257, 0.5), (513, 0.25)]
    master_sock.sendto(B_REPLY.pack(0, Pid.MRT, 0, 1, 7, tuple(x for k in range(20) for x in (k, k / 4, 1))),
                       module_sock.getsockname())  # fmt: skip
    reply = decode(module_sock.recv(2048)).body
    assert isinstance(reply, Reply) and [i.value for i in reply.items] == [k / 4 for k in range(20)]
    assert b_of([k / 4 for k in range(20)]).v[-1] == 19 / 4


@pytest.mark.slow
def test_the_arm_tracks_with_every_message_over_sockets_as_it_does_in_memory(link) -> None:
    ref = circle(radius=0.08, speed=0.5)
    memory = track_vdc(ref)
    wire = track_vdc(ref, link=link)
    # the same control law; only the 32-bit rounding of the values on the wire differs
    assert abs(wire.tool_error_mm_max - memory.tool_error_mm_max) < 1e-3
    assert np.abs(wire.q - memory.q).max() < 1e-5
    cycles = len(ref.t)
    assert link.counters.datagrams == 24 * cycles and link.counters.refused == 0
    assert len(link.counters.transit_ns) == cycles - 1  # (one figure a cycle, the last still open)


@pytest.mark.slow
def test_junk_on_the_wire_is_refused_and_guessed_and_the_arm_tracks_on(link) -> None:
    """Every 50th datagram arrives corrupted (a flipped byte: its CRC fails): the receiver refuses it
    and the loop guesses as for a lost one (no retry); the arm keeps to the aim."""
    carry, n = link._carry, [0]

    def corrupting(src, dst, data: bytes) -> bytes:
        n[0] += 1
        got = carry(src, dst, data)
        return got[:20] + bytes([got[20] ^ 0x40]) + got[21:] if n[0] % 50 == 0 else got

    link._carry = corrupting
    ref = circle(radius=0.08, speed=0.5)
    run = track_vdc(ref, Faults(), link=link)
    assert link.counters.refused == n[0] // 50 > 100
    assert sum(run.guessed.values()) == link.counters.refused  # each refusal guessed, none retried
    assert run.tool_error_mm_max < 2.0
