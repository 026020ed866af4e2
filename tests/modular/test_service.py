"""The modular robot as a service of the cell: `cell up` with "modular", a task script moving it, `cell
modular plug | unplug | status | move`, its modules in `cell status`, drawn in the Rerun recording."""

from __future__ import annotations

import asyncio
import json
import os
import signal
import time

import pytest
from rerun.chunk import RrdReader

from tests.conftest import run_cell


@pytest.mark.slow
async def test_a_task_script_moves_it_and_the_cli_unplugs_and_plugs_a_module(start_cell, tmp_path) -> None:
    rrd = tmp_path / "modular.rrd"
    cell = await start_cell(
        run=["bus", "modular", "recorder"],
        # (its messages as SnP-MrT packets between UDP sockets, not handed over in memory)
        sections={"recorder": {"mode": "save", "path": str(rrd)}, "modular": {"transport": "snp"}},
    )
    cfg = str(cell.path)
    script = tmp_path / "move.py"
    script.write_text(
        "import asyncio, json, time\n"
        "async def main(cell):\n"
        "    circle = asyncio.create_task(cell.modular.move(path='circle'))\n"
        "    while (a := await cell.modular.status()).motion == '':  # (planned, not started yet)\n"
        "        await asyncio.sleep(0.01)\n"
        "    ta = time.monotonic()\n"
        "    await asyncio.sleep(1.0)  # (a window of the 2.4 s motion, measured by the clock)\n"
        "    b, tb = await cell.modular.status(), time.monotonic()\n"
        "    r = await circle\n"
        "    j = await cell.modular.move([0.3, -1.2, 1.2, -1.6, -1.5, 0.2], speed=1.5)\n"
        "    st = await cell.modular.status()\n"
        "    print(json.dumps({'circle': r.tool_error_mm_max, 'joints': j.tool_error_mm_max,\n"
        "                      'q': list(st.q), 'moving': b.motion != '',\n"
        "                      'hz': (b.cycles - a.cycles) / (tb - ta), 'us': b.cycle_us_mean,\n"
        "                      'late': b.late_cycles - a.late_cycles, 'cycles': st.cycles}))\n"
    )
    done = await asyncio.to_thread(run_cell, "run", str(script), "--config", cfg, timeout=60)
    assert done.returncode == 0, done.stderr[-2000:]
    got = json.loads(done.stdout.strip().splitlines()[-1])
    assert got["circle"] < 2.0 and got["joints"] < 2.0  # the aim for the tool with no loss, mm
    assert max(abs(a - b) for a, b in zip(got["q"], [0.3, -1.2, 1.2, -1.6, -1.5, 0.2], strict=True)) < 2e-3
    # its cycles run on the wall clock's 1 ms grid, over a second of the circle by the clock (two status
    # round trips of a few ms at the window's ends): at 1 kHz, or what fell behind is counted late (in
    # Python with its messages as SnP packets a cycle here may cost more than its millisecond)
    assert got["moving"] and got["hz"] <= 1100 and (got["hz"] >= 900 or got["late"] > 0), got
    # a module pulled: the arm stops and holds, motions are refused saying why; `cell status` shows it
    out = await asyncio.to_thread(run_cell, "modular", "unplug", "j2", "--config", cfg)
    assert out.returncode == 0 and "j2      unplugged" in out.stdout, out.stdout + out.stderr
    refused = await asyncio.to_thread(
        run_cell, "modular", "move", "--joints", "0", "-1.5708", "1.5708", "-1.5708", "-1.5708", "0",
        "--config", cfg,
    )  # fmt: skip
    assert refused.returncode == 2 and "refused: module j2 unplugged" in refused.stderr, refused.stderr
    status = await asyncio.to_thread(run_cell, "status", "--config", cfg)
    assert "MODULAR ROBOT (j1 running  j2 unplugged  j3 running" in status.stdout, status.stdout
    st = json.loads((await asyncio.to_thread(run_cell, "status", "--json", "--config", cfg)).stdout)
    counters = next(s["last"]["counters"] for s in st["services"] if s["name"] == "modular")
    # every cycle's 24 messages went as packets (by the script's status; j2's 4 a cycle stop once pulled)
    assert counters["modular.datagrams"] >= 24 * (got["cycles"] - 100) and counters["modular.refused"] == 0
    bad = await asyncio.to_thread(run_cell, "modular", "plug", "j7", "--config", cfg)
    assert bad.returncode == 2 and "no module 'j7'" in bad.stderr
    out = await asyncio.to_thread(run_cell, "modular", "plug", "j2", "--config", cfg)
    assert out.returncode == 0 and "j2      running" in out.stdout
    moved = await asyncio.to_thread(
        run_cell, "modular", "move", "--joints", "0", "-1.5708", "1.5708", "-1.5708", "-1.5708", "0",
        "--speed", "2", "--config", cfg,
    )  # fmt: skip
    assert moved.returncode == 0 and moved.stdout.startswith("joints: "), moved.stderr
    guessed = int(moved.stdout.split(" messages guessed")[0].rsplit(" ", 1)[1])
    assert guessed == 0  # (j2 back: nothing guessed in this motion)
    code, _, _, err = cell.stop()
    assert code == 0, err[-2000:]
    rows: dict[str, int] = {}
    for chunk in RrdReader(rrd).stream():
        rows[str(chunk.entity_path)] = rows.get(str(chunk.entity_path), 0) + chunk.num_rows
    assert rows.get("/modular/arm", 0) > 100  # the arm drawn at publish_hz through the run
    assert rows.get("/modular/tool_error_mm", 0) > 100 and rows.get("/modular/cycle_us/C", 0) > 100
    assert rows.get("/modular/guessed/j2", 0) > 0


def test_the_live_view_draws_the_modular_robot_only_where_it_runs() -> None:
    """Rerun draws only what a view of the blueprint holds: the arm in the cell's 3D view and its cycle
    in a tab of its own when the service runs (its entities were logged, but drawn nowhere, before)."""
    from cell.recorder.blueprint import cell_blueprint

    def views(modular: bool) -> tuple[list[str], list[str]]:
        cell = cell_blueprint(["r1"], camera=False, modular=modular).root_container.contents[0]
        space, side = cell.contents
        return list(space.contents), [tab.name for tab in side.contents[0].contents]

    assert views(True) == (["robots/**", "modular/**"], ["r1", "modular"])
    assert views(False) == (["robots/**"], ["r1"])


# (make perf: its aims hold only on a machine whose timers wake on time; on a VM whose idle vCPUs stall
# a wake-up for milliseconds several times a second it fails as it did before issue 53's work: p99.9 of
# a 1 ms clock_nanosleep 2-12 ms there, measured the day it was moved)
@pytest.mark.perf
async def test_on_the_snp_cycle_its_processes_move_the_arm_and_a_pulled_module_stops_it(
    start_cell, tmp_path
) -> None:
    """[modular] transport "cycle": the SnP cycle's master and six modules in processes of their own,
    each module with its own clock (off by up to 2 ms, servoed by SnP-TSP), the arm in MuJoCo; the
    modules compute their [C, D] by the master, locally, and with their neighbour's force (out to the tip)."""
    rrd = tmp_path / "cycle.rrd"
    where = ["master", "master", "local", "neighbour", "neighbour", "neighbour"]
    cell = await start_cell(
        run=["bus", "modular", "recorder"],
        sections={
            "recorder": {"mode": "save", "path": str(rrd)},
            "modular": {"transport": "cycle", "where": where},
        },
    )
    cfg = str(cell.path)
    goal = [0.3, -1.3, 1.4, -1.6, -1.4, 0.2]
    script = tmp_path / "move.py"
    script.write_text(
        "import json\n"
        "async def main(cell):\n"
        f"    j = await cell.modular.move({goal}, speed=1.0)\n"
        "    st = await cell.modular.status()\n"
        "    print(json.dumps({'joints': j.tool_error_mm_max, 'cycles': j.cycles, 'q': list(st.q),\n"
        "                      'offsets': [m.clock_offset_us for m in st.modules],\n"
        "                      'where': [m.where for m in st.modules],\n"
        "                      'transport': st.transport}))\n"
    )
    done = await asyncio.to_thread(run_cell, "run", str(script), "--config", cfg, timeout=60)
    assert done.returncode == 0, done.stderr[-2000:]
    got = json.loads(done.stdout.strip().splitlines()[-1])
    assert got["transport"] == "cycle" and got["joints"] < 5.0 and got["cycles"] > 300
    assert got["where"] == where
    assert max(abs(a - b) for a, b in zip(got["q"], goal, strict=True)) < 5e-3
    assert all(abs(o) < 50.0 for o in got["offsets"]), got["offsets"]  # (started up to 2 ms off)
    # j3's socket pulled from the network: the master loses it, the arm holds, motions are refused
    out = await asyncio.to_thread(run_cell, "modular", "unplug", "j3", "--config", cfg)
    assert out.returncode == 0 and "j3      unplugged" in out.stdout, out.stdout + out.stderr
    home = ["0", "-1.5708", "1.5708", "-1.5708", "-1.5708", "0"]
    goal_args = [str(x) for x in goal]
    for _ in range(100):  # (the master's FDIR: silent, then lost after 50 ms; its report every 20 ms)
        refused = await asyncio.to_thread(run_cell, "modular", "move", "--joints", *home, "--config", cfg)
        if refused.returncode == 2:
            break
    assert refused.returncode == 2 and "module j3 unplugged" in refused.stderr, refused.stderr
    status = await asyncio.to_thread(run_cell, "status", "--config", cfg)
    assert "j3 unplugged" in status.stdout, status.stdout
    # plugged back: found by the master's exploration, configured, its clock synced, included
    out = await asyncio.to_thread(run_cell, "modular", "plug", "j3", "--config", cfg)
    assert out.returncode == 0, out.stderr
    for _ in range(100):
        moved = await asyncio.to_thread(
            run_cell, "modular", "move", "--joints", *home, "--speed", "2", "--config", cfg
        )
        if moved.returncode != 2:
            break
    assert moved.returncode == 0 and moved.stdout.startswith("joints: "), moved.stdout + moved.stderr
    # the cycle's master process killed mid-motion: the service fails saying so, the motion's request
    # is answered at once (its supervisor's event on the bus), not at its 120 s timeout; the service
    # is restarted, and moves again
    slow = asyncio.ensure_future(asyncio.to_thread(
        run_cell, "modular", "move", "--joints", *goal_args, "--speed", "0.05", "--config", cfg
    ))  # fmt: skip
    for _ in range(200):
        shown = await asyncio.to_thread(run_cell, "modular", "status", "--config", cfg)
        if "moving:" in shown.stdout:
            break
    assert "moving:" in shown.stdout, shown.stdout + shown.stderr
    st = json.loads((await asyncio.to_thread(run_cell, "status", "--json", "--config", cfg)).stdout)
    service_pid = next(s["last"]["pid"] for s in st["services"] if s["name"] == "modular")
    children = [p for p in _children(service_pid) if b"spawn_main" in _cmdline(p)]
    assert len(children) == 2, children  # (the master's process, then the modules')
    os.kill(children[0], signal.SIGKILL)
    t0 = time.monotonic()
    moving = await slow
    assert moving.returncode == 1 and "service 'modular' failed" in moving.stderr, moving.stderr
    assert "the cycle's master process ended" in moving.stderr and time.monotonic() - t0 < 20.0
    last = await _restarted(cfg)
    assert last.get("restarts", 0) >= 1 and "the cycle's master process ended" in last["last_error"], last
    for _ in range(100):  # (refused while its new modules join the cycle)
        moved = await asyncio.to_thread(
            run_cell, "modular", "move", "--joints", *goal_args, "--speed", "2", "--config", cfg
        )
        if moved.returncode != 2:
            break
    assert moved.returncode == 0, moved.stdout + moved.stderr
    assert not any(p in children for p in _children(last["pid"]))  # (its new processes)
    code, _, _, err = cell.stop()
    assert code == 0, err[-2000:]
    assert not [p for p in children[1:] if _cmdline(p)]  # the old modules' process ended
    rows: dict[str, int] = {}
    for chunk in RrdReader(rrd).stream():
        rows[str(chunk.entity_path)] = rows.get(str(chunk.entity_path), 0) + chunk.num_rows
    assert rows.get("/modular/arm", 0) > 50
    assert rows.get("/modular/clock_offset_us/j1", 0) > 10 and rows.get("/modular/cycle_us/j6", 0) > 10


# (make perf: its aims hold only on a machine whose timers wake on time; on a VM whose idle vCPUs stall
# a wake-up for milliseconds several times a second it fails as it did before issue 53's work: p99.9 of
# a 1 ms clock_nanosleep 2-12 ms there, measured the day it was moved)
@pytest.mark.perf
async def test_over_the_routers_a_task_script_moves_it_and_a_pulled_module_comes_back(
    start_cell, tmp_path
) -> None:
    """[modular] network "routed": the cycle's datagrams through the two routers' process (a third
    process of the service), each module known by its return address; unplugged and plugged back,
    a module is found again through them."""
    cell = await start_cell(
        run=["bus", "modular"], sections={"modular": {"transport": "cycle", "network": "routed"}}
    )
    cfg = str(cell.path)
    st = json.loads((await asyncio.to_thread(run_cell, "status", "--json", "--config", cfg)).stdout)
    pid = next(s["last"]["pid"] for s in st["services"] if s["name"] == "modular")
    assert len([c for c in _children(pid) if b"spawn_main" in _cmdline(c)]) == 3  # master, modules, routers
    goal = ["0.3", "-1.3", "1.4", "-1.6", "-1.4", "0.2"]
    for _ in range(100):  # (refused while the modules join the cycle)
        moved = await asyncio.to_thread(
            run_cell, "modular", "move", "--joints", *goal, "--speed", "2", "--config", cfg
        )
        if moved.returncode != 2:
            break
    assert moved.returncode == 0 and moved.stdout.startswith("joints: "), moved.stdout + moved.stderr
    out = await asyncio.to_thread(run_cell, "modular", "unplug", "j2", "--config", cfg)
    assert out.returncode == 0, out.stderr
    for _ in range(100):
        refused = await asyncio.to_thread(run_cell, "modular", "move", "--joints", *goal, "--config", cfg)
        if refused.returncode == 2:
            break
    assert refused.returncode == 2 and "module j2 unplugged" in refused.stderr, refused.stderr
    assert (await asyncio.to_thread(run_cell, "modular", "plug", "j2", "--config", cfg)).returncode == 0
    home = ["0", "-1.5708", "1.5708", "-1.5708", "-1.5708", "0"]
    for _ in range(100):
        moved = await asyncio.to_thread(
            run_cell, "modular", "move", "--joints", *home, "--speed", "2", "--config", cfg
        )
        if moved.returncode != 2:
            break
    assert moved.returncode == 0, moved.stdout + moved.stderr
    # the routers' process killed: the service fails saying so, and is restarted with a new network
    routers = min(c for c in _children(pid) if b"spawn_main" in _cmdline(c))  # (started first)
    os.kill(routers, signal.SIGKILL)
    last = await _restarted(cfg)
    assert last.get("restarts", 0) >= 1 and "the cycle's routers process ended" in last["last_error"], last
    code, _, _, err = cell.stop()
    assert code == 0, err[-2000:]


async def _restarted(cfg: str) -> dict:
    """The modular service's last status once it has been restarted and runs again (after its
    backoff, [services] backoff_initial_s), or as it stands after 100 looks."""
    for _ in range(100):
        st = json.loads((await asyncio.to_thread(run_cell, "status", "--json", "--config", cfg)).stdout)
        last = next(s["last"] for s in st["services"] if s["name"] == "modular")
        if last.get("restarts", 0) >= 1 and last.get("state") == "SERVICE_STATE_RUNNING":
            break
        await asyncio.sleep(0.1)
    return last


def _children(pid: int) -> list[int]:
    """The processes whose parent is pid (from /proc)."""
    out = []
    for entry in os.listdir("/proc"):
        if entry.isdigit():
            try:
                with open(f"/proc/{entry}/stat", "rb") as f:
                    stat = f.read()
            except OSError:
                continue
            if int(stat.rsplit(b")", 1)[1].split()[1]) == pid:
                out.append(int(entry))
    return sorted(out)


def _cmdline(pid: int) -> bytes:
    try:
        with open(f"/proc/{pid}/cmdline", "rb") as f:
            return f.read()
    except OSError:
        return b""
