"""The UR interfaces of a group of arms (cell.ur.server.URInterfaces) without sockets: which arms cost
the ticks anything, and what a program leaves behind when it ends."""

from __future__ import annotations

import time

import numpy as np

from cell.config import load_config
from cell.robot import udp
from cell.robot.emulator import RobotGroup
from cell.ur.arm import RuntimeState
from cell.ur.server import URInterfaces
from tests.conftest import cell_overrides

ARMS = 40


def test_only_arms_with_a_client_or_a_program_are_looked_at_each_tick() -> None:
    robots = [
        {"id": 1 + i, "name": f"k{i}", "skill_port": 3000 + i, "backend": "kinematic", "socket": "shared"}
        for i in range(ARMS)
    ]
    cfg = load_config(overrides={**cell_overrides(), "robots": robots})
    sink = udp.open_socket("127.0.0.1")
    host, port = sink.getsockname()
    g = RobotGroup(cfg.robots, f"{host}:{port}", tick="python")
    try:
        ur = URInterfaces(g, cfg)
        assert not ur.busy() and not ur.active  # a fleet with no client: nothing per tick
        arm = ur.arms[7]
        arm.run("def go():\n  set_standard_digital_out(1, True)\n  sleep(0.02)\nend\n")
        assert ur.busy() and ur.active == {arm}
        # the program's ticks, its end, then the datagram program back (RESTART_S on, by the clock)
        deadline = give_up = time.monotonic()
        give_up += 10.0
        while ur.active:
            assert time.monotonic() < give_up, f"the arm never left the per-tick set: {arm.state.runtime}"
            deadline += g.period
            stopping, resuming = g.tick(deadline)
            ur.after_tick(g, stopping, resuming)
        assert not ur.busy() and arm.state.runtime == RuntimeState.PLAYING  # (the datagram program again)
        # its outputs stayed with the group as the arm left the set; no other arm's changed
        assert g.digital_out[7] == 2 and not np.delete(g.digital_out, 7).any()
    finally:
        g.close()
        sink.close()


def test_remote_control_is_what_the_config_says_as_a_fresh_ursims_is_false() -> None:
    """`[ur] remote_control`: the dashboard's `is in remote control` (UR's client library's
    operational_mode test expects URSim's false); the arm takes programs either way, as URSim does."""
    robots = [{"id": 1, "name": "r1", "skill_port": 3000, "backend": "kinematic"}]
    sink = udp.open_socket("127.0.0.1")
    host, port = sink.getsockname()
    for remote, said in ((True, "true"), (False, "false")):
        cfg = load_config(overrides={**cell_overrides(), "robots": robots, "ur": {"remote_control": remote}})
        g = RobotGroup(cfg.robots, f"{host}:{port}", tick="python")
        try:
            ur = URInterfaces(g, cfg)
            arm = ur.arms[0]
            assert ur.dashboard_of(arm).handle("is in remote control") == said
            arm.run('textmsg("hello")\n')
            assert arm.runner is not None
        finally:
            g.close()
    sink.close()
