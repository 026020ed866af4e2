"""`cell chaos`: the default cell in --processes mode, driven through motions while faults hit it.

For each fault (cell.chaos.faults) the campaign waits until the cell is
healthy and the robots rest, starts a motion on every robot through its
skill server (a move and a `break` that waits for the arrival), injects the
fault mid-motion, and watches: what each waiting command is answered and
when, the robots' true joint states and protective stops (from the bus), the
counters and restarts in `cell status`, and whether motions work again.  It
then judges each promise of faults.PROMISES that applies and reports, per
fault, whether all held, the time to detect (the first reaction: a stop, a
`stopped` answer, a status change) and the time to recover (until a motion
on every robot worked again).

The controller reaches the bus through a DelayLink run here (its process
group's bus override), so its link can be slowed and made lossy on demand.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import socket
import subprocess
import time
import tomllib
from dataclasses import asdict, replace
from pathlib import Path
from typing import Any

import numpy as np

from cell import models
from cell.bus import Bus, BusError
from cell.bus.delay import DelayLink
from cell.cellproc import default_robots, ok_services, running_cell
from cell.chaos.faults import PROMISES, Fault, Hang, Kill, SlowLink, SwitchDown, catalogue
from cell.chaos.observer import REST, EStop, FaultResult, Observer, Outcome
from cell.config import CellConfig, load_config
from cell.launcher import fetch_status
from cell.ports import free_port
from cell.rlink.client import EventClient
from cell.sched import most_stolen, stolen_seconds
from cell.skills.client import ConnectionLost, MoveJoints, RobotClient, SetSpeed, SkillError
from cell.status import Health
from cell.v1 import health_pb2

log = logging.getLogger("cell.chaos")
FAULT_S = 6.0  # how long one fault takes on this machine kind (injected, judged, the cell whole again)

LUNGE = 2e-3  # rad: moving further than this from where it came to rest is an unplanned motion
ARRIVED = 2e-3  # rad: a motion answered done ended within this of its goal
SWING = np.array([0.6, -0.25, 0.25, 0.0, 0.0, 0.5])  # rad: the motion driven back and forth
ESTOP_AT_S = 1.2  # the e-stop comes this long after the fault (after answered_1s's second, in the fault)
# beyond its braking: the order to the drives (p99 2 ms), the arm following its braking drive (the
# MuJoCo joints trail their reference by 30-40 ms) and the truth sample (10 ms) that shows it stand
ESTOP_MARGIN_MS = 60.0
REPORT_MS = 100.0  # a robot's own report of standing comes later: still is < 1 mrad/s, rest < 2


class Campaign:
    def __init__(self, config: CellConfig, link: DelayLink, observer: Observer) -> None:
        self.config = config
        self.link = link
        self.obs = observer
        self.robots = [r.name for r in config.robots]
        self.home = {r.name: np.array(r.q0, np.float64) for r in config.robots}
        self.window_ms = {r.name: 1e3 / r.command_hz for r in config.robots}
        self.tick_ms = {r.name: 1e3 / r.status_hz for r in config.robots}
        self.watchdog = {r.name: r.watchdog_windows for r in config.robots}
        self.out = {r: False for r in self.robots}  # which end of the swing each robot is at
        self.last_status: health_pb2.CellStatus | None = None

    # --- the cell's state ------------------------------------------------------------------------

    async def status(self, timeout: float = 1.0) -> health_pb2.CellStatus | None:
        with contextlib.suppress(BusError, OSError):
            return await fetch_status(self.config, timeout=timeout)
        return None

    async def healthy(
        self, timeout: float = 60.0, dead: dict[str, int] | None = None
    ) -> health_pb2.CellStatus:
        """Until every service is ok and every robot rests (and the services in `dead` run in a process
        other than the pid given: a status taken before the launcher has seen a kill is no recovery);
        the status then."""
        want = set(self.config.services.run)
        dead = dead or {}
        async with asyncio.timeout(timeout):
            while True:
                st = self.last_status = await self.status()
                if (
                    st is not None
                    and want <= ok_services(st)
                    and not any(s.last.pid == dead.get(s.name) for s in st.services)
                    and all(self.obs.at_rest(r) for r in self.robots)
                ):
                    return st
                await asyncio.sleep(0.1)

    async def counted(
        self, st: health_pb2.CellStatus, key: str, before: dict[str, float], timeout: float = 3.0
    ) -> health_pb2.CellStatus:
        """The first status (from st on, for at most timeout) whose counter `key` grew past before's."""
        with contextlib.suppress(TimeoutError):
            async with asyncio.timeout(timeout):
                while _counters(st).get(key, 0.0) <= before.get(key, 0.0):
                    await asyncio.sleep(0.1)
                    st = await self.status() or st
        return st

    # --- driving -----------------------------------------------------------------------------------

    def goal(self, robot: str) -> np.ndarray:
        return self.home[robot] + (0.0 if self.out[robot] else 1.0) * SWING

    async def drive(self, robot: str, goal: np.ndarray, t_fault: list[int], speed: float = 60.0) -> Outcome:
        """A move and its break on a fresh connection to the robot's skill server; what it was answered."""
        rc = self.config.robot(robot)
        client = RobotClient(robot, self.config.skills.host, rc.skill_port)

        def since() -> float:
            return (time.monotonic_ns() - t_fault[0]) / 1e9 if t_fault else -1.0

        try:
            async with asyncio.timeout(30.0):
                await client.connect(timeout=10.0)
                try:
                    await client.cmdexec(SetSpeed(speed))
                    await client.cmdexec(MoveJoints(tuple(np.degrees(goal).tolist())))
                finally:
                    await client.close()
        except SkillError as exc:
            return Outcome(robot, exc.code, f"{exc.skill}: {exc.text}", since())
        except ConnectionLost as exc:
            return Outcome(robot, "lost", str(exc), since())
        except TimeoutError:
            return Outcome(robot, "timeout", "no answer within 30 s", since())
        except OSError as exc:
            return Outcome(robot, "lost", f"could not connect: {exc}", since())
        self.out[robot] = not self.out[robot]
        return Outcome(robot, "done", "", since())

    async def moving(self, timeout: float = 3.0) -> None:
        """Until every robot is under way (or timeout)."""
        with contextlib.suppress(TimeoutError):
            async with asyncio.timeout(timeout):
                while not all((x := self.obs.latest(r)) is not None and x[1] > 0.1 for r in self.robots):
                    await self.obs.sample()

    async def estop(self) -> EStop:
        """An e-stop of every robot over the Responsive Link, as `cell estop` sends it; until each
        robot reports it stands (or 5 s)."""
        t0, steal = time.monotonic_ns(), stolen_seconds()
        names = {r.id: r.name for r in self.config.robots}
        try:
            async with EventClient(self.config) as ev:
                ms = await ev.estop(timeout=5.0)
        except (TimeoutError, OSError) as exc:
            return EStop(t0, {}, str(exc))
        return EStop(t0, {names[i]: v for i, v in ms.items()}, stolen_ms=most_stolen(steal) * 1e3)

    async def resume(self) -> None:
        with contextlib.suppress(TimeoutError, OSError):
            async with EventClient(self.config) as ev:
                await ev.resume(timeout=10.0)

    def braking(self, robot: str) -> float:
        """The robot's slowest joint's deceleration (rad/s^2): its braking, and the most its speed
        can change by in a second."""
        return float(np.min(models.get(self.config.robot(robot).model).a_max))

    def estop_bound_ms(self, robot: str, speed: float) -> float:
        """How long a robot may take to stand after an e-stop at `speed` (rad/s, its fastest joint, at
        most: see _estop_held): its full braking from there, and ESTOP_MARGIN_MS."""
        return speed / self.braking(robot) * 1e3 + ESTOP_MARGIN_MS

    # --- faults ------------------------------------------------------------------------------------

    def pids(self, st: health_pb2.CellStatus) -> dict[str, int]:
        return {s.name: s.last.pid for s in st.services if s.last.pid}

    def switch_port(self, *setting: str) -> None:
        """`ip link set` on the XDP switch's port to the robots (its end of the veth pair): down, up,
        xdpgeneric off."""
        x = self.config.dataplane.switch
        subprocess.run(
            ["ip", "-n", x.netns, "link", "set", "dev", f"{x.veth}1", *setting], check=True, timeout=10
        )

    async def run(self, fault: Fault) -> FaultResult:
        held: dict[str, bool] = {}
        detail: dict[str, str] = {}
        before = await self.healthy()
        pids = self.pids(before)
        counters_before = _counters(before)
        restarts_before = {s.name: s.last.restarts for s in before.services}
        t_fault: list[int] = []
        links = [a for a in fault.actions if isinstance(a, SlowLink)]
        others = [a for a in fault.actions if not isinstance(a, SlowLink)]
        for link in links:  # motions planned over the slow link: it comes first
            await link.inject(self, pids)
        goals = {r: self.goal(r) for r in self.robots}
        drives = [asyncio.ensure_future(self.drive(r, goals[r], t_fault)) for r in self.robots]
        await self.moving()
        if not others:  # (the fault's time is when the robots move: their rest before is no lunge)
            t_fault.append(time.monotonic_ns())
        stale_seen: set[str] = set()
        try:
            if others:
                t_fault.append(time.monotonic_ns())
                for a in others:
                    await a.inject(self, pids)
                if any(isinstance(a, SwitchDown) for a in others):  # (down once `ip` has returned: the
                    t_fault[0] = time.monotonic_ns()  # command's few ms are not the robots')
            deadline = time.monotonic() + fault.seconds
            outcomes: list[Outcome] = []
            pending = set(drives)
            ended = False
            stopping: asyncio.Future[EStop] | None = None
            wants_estop = "estop" in fault.promises
            while pending or not ended or (wants_estop and (stopping is None or not stopping.done())):
                if wants_estop and stopping is None and time.monotonic_ns() - t_fault[0] >= ESTOP_AT_S * 1e9:
                    stopping = asyncio.ensure_future(self.estop())
                if not ended and time.monotonic() >= deadline:
                    for a in fault.actions:
                        a.end(self, pids)
                    ended = True
                wait = 0.1 if ended else min(0.1, max(0.0, deadline - time.monotonic()))
                if pending:
                    done, pending = await asyncio.wait(pending, timeout=wait)
                    outcomes += [d.result() for d in done]
                else:
                    await asyncio.sleep(wait)
                hanging = not ended and any(isinstance(a, Hang) for a in others)
                if hanging:
                    if (st := await self.status(timeout=0.3)) is not None:
                        stale_seen |= {s.name for s in st.services if s.health == Health.STALE}
                    else:
                        stale_seen.add("bus")  # no status at all: the bus is down
        finally:
            for a in fault.actions:
                a.end(self, pids)
        t_end = time.monotonic_ns()
        estop = stopping.result() if stopping is not None else None
        # recovery: every service ok again, then a motion on every robot (back where each came from)
        recovered_st = None
        with contextlib.suppress(TimeoutError):
            killed = {a.target: pids[a.target] for a in fault.actions if isinstance(a, Kill)}
            recovered_st = await self.healthy(timeout=60.0, dead=killed)
        if "reattached" in fault.promises and recovered_st is not None:  # (counters come with heartbeats)
            recovered_st = await self.counted(recovered_st, "dataplane.xdp.reattached", counters_before)
        t_resume = time.monotonic_ns()
        if estop is not None:  # (released once the cell is whole again, as an operator would)
            await self.resume()
        t_check = time.monotonic_ns()
        back = await asyncio.gather(*(self.drive(r, self.goal(r), [t_check]) for r in self.robots))
        t_recovered = time.monotonic_ns()
        t0 = t_fault[0]

        # --- judgement -----------------------------------------------------------------------------
        killed_skills = any(isinstance(a, Kill) and a.target == "skills" for a in fault.actions)
        ok_status = {"done", "stopped"} | ({"lost"} if killed_skills else set())
        bad = [o for o in outcomes if o.status not in ok_status]
        held["answered"] = not bad and len(outcomes) == len(self.robots)
        detail["answered"] = "; ".join(
            f"{o.robot}: {o.status} after {o.after_s:.2f} s {o.text}" for o in outcomes
        )
        if "answered_1s" in fault.promises:
            # (those the e-stop answered are the e-stop's: it comes after this promise's second)
            by_estop = (estop.t_ns - t0) / 1e9 if estop is not None else float("inf")
            stopped = [o for o in outcomes if o.status == "stopped" and o.after_s < by_estop]
            late = [o.robot for o in stopped if o.after_s > 1.0]
            held["answered_1s"] = not late and (bool(stopped) or killed_skills)
            detail["answered_1s"] = f"late: {late}" if late else ("" if stopped else "none answered stopped")
        # completed: done means at the goal; a lost connection (skills killed) must still end at the goal
        # or be at rest where a stop left it (the controller's new start stops it)
        far = []
        for o in outcomes:
            if o.status in ("done", "lost"):
                last = self.obs.latest(o.robot)
                q_at = self._q_near(o.robot, t_end) if last is not None else None
                if o.status == "done" and (q_at is None or np.abs(q_at - goals[o.robot]).max() > ARRIVED):
                    far.append(o.robot)
            if o.status == "lost":  # whether it moved is for us to find out: it went on to its goal
                self.out[o.robot] = np.abs(self._q_near(o.robot, t_check) - goals[o.robot]).max() < ARRIVED
        held["completed"] = not far
        detail["completed"] = f"done but not at the goal: {far}" if far else ""
        # no lunge between the fault and the recovery check
        # (from each robot's answer on: a motion stalled on a late TP rests, then goes on as planned)
        answered_at = {o.robot: t0 + int(max(0.0, o.after_s) * 1e9) for o in outcomes}
        lunge_at = {r: self.obs.lunge(r, answered_at.get(r, t0), t_check) for r in self.robots}
        lunges = {r: moved for r, (moved, _, _) in lunge_at.items()}
        held["no_lunge"] = all(v < LUNGE for v in lunges.values())
        detail["no_lunge"] = ", ".join(
            f"{r} moved {m * 1e3:.2f} mrad (up to {v:.3f} rad/s at {t:.2f} s)"
            for r, (m, v, t) in lunge_at.items()
        )
        # the robots' protective stops after the fault
        stopped_at = [((t - t0) / 1e6, r) for t, r in self.obs.stops if t0 <= t <= t_check]  # (ms, robot)
        stops = [ms for ms, _ in stopped_at]
        first: dict[str, float] = {}  # each robot's first stop: the one the fault caused
        for ms, r in stopped_at:
            first[r] = min(ms, first.get(r, ms))
        if "stop_windows" in fault.promises:
            # (a robot looks at its watchdog on its ticks: the one after the last window ends it)
            bound = max((self.watchdog[r] + 1) * self.window_ms[r] + self.tick_ms[r] for r in self.robots)
            held["stop_windows"] = len(first) == len(self.robots) and max(first.values()) <= bound
            detail["stop_windows"] = f"stops after {sorted(first.values())} ms (bound {bound:.0f} ms)"
        if "reattached" in fault.promises:
            c1 = _counters(recovered_st)
            grew = _grew(
                counters_before, c1, ("dataplane.xdp.reattached", "dataplane.xdp.answered_in_user_space")
            )
            held["reattached"] = grew.get("dataplane.xdp.reattached", 0) >= 1
            detail["reattached"] = f"grew: {grew}"
        if "kernel_answers" in fault.promises:  # (the program in the kernel kept the robots commanded)
            held["kernel_answers"] = not stops
            who = sorted((round(ms, 1), r) for ms, r in stopped_at)
            detail["kernel_answers"] = f"protective stops (ms after the fault, robot): {who}" if stops else ""
        after = recovered_st
        if "packet_path" in fault.promises:
            c0, c1 = counters_before, _counters(after) if after is not None else {}
            grew = _grew(c0, c1, ("robots.protective_stops", "dataplane.dropped", "dataplane.dropped.stop"))
            asked = grew.pop("dataplane.dropped.stop", 0.0)  # (the e-stop's: asked for)
            if grew.get("dataplane.dropped", 0.0) - asked <= 0:
                grew.pop("dataplane.dropped", None)
            held["packet_path"] = not grew and not stops
            # (the kernel's RT throttling stops the packet path's processes for up to 50 ms: said)
            rt = _grew(c0, c1, ("robots.process.rt.held", "dataplane.process.rt.held"))
            detail["packet_path"] = (f"grew: {grew}" if grew else "") + (
                f"; RT throttled: {rt}" if rt else ""
            )
        if estop is not None:
            held["estop"], detail["estop"] = self._estop_held(fault, estop, t0, t_resume)
        if "status" in fault.promises:
            held["status"], detail["status"] = self._status_held(fault, after, restarts_before, stale_seen)
        works = [o for o in back if o.status == "done"]
        held["recovered"] = recovered_st is not None and len(works) == len(self.robots)
        detail["recovered"] = "; ".join(f"{o.robot}: {o.status} {o.text}" for o in back if o.status != "done")
        # the first reaction: a stopped answer, a protective stop, or a service event
        # (a motion planned over a slow link may be stopped before it moved: that is at the fault)
        reactions = [max(0.0, o.after_s) * 1e3 for o in outcomes if o.status == "stopped"] + stops
        reactions += [(t - t0) / 1e6 for t, _, _, _ in self.obs.service_events if t >= t0]
        detect = min(reactions) if reactions else None
        recover = (t_recovered - t0) / 1e9
        answers = [o.after_s for o in outcomes if o.status == "stopped"]
        figures = {
            "estop_still_ms_max": max(estop.still_ms.values(), default=0.0) if estop else 0.0,
            # (the slowest robot's first stop; a later one, as the restarted data plane takes over, is
            # not the fault's reaction: it counts in the packet path's promise where there is one)
            "stop_ms_max": max(first.values(), default=0.0),
            "moved_after_rest_mrad": max(lunges.values()) * 1e3,
            "stopped_answer_s_max": max(answers) if answers else 0.0,
        }
        return FaultResult(fault.name, held, detail, detect, recover, figures)

    def _estop_held(self, fault: Fault, e: EStop, t_fault: int, t_resume: int) -> tuple[bool, str]:
        """Every robot stood within its bound of the order (its braking, ESTOP_MARGIN_MS and what the
        hypervisor stole meanwhile), by its truth (no motion from then until
        the release), or where no truth was heard (the bus down) by its own report over the
        Responsive Link (REPORT_MS later).  No order gets through a killed or hung hub: the link's
        watchdog must then stop the robots ([rlink] watchdog_s after the fault, +1/4 of it: how often a
        node looks)."""
        rl = self.config.rlink
        through = bool(e.still_ms) and max(e.still_ms.values()) < 1e3
        if "rlink" in fault.services and not through:  # (a node looks at its watchdog 4 times in one)
            since = t_fault + int(rl.watchdog_s * 1.25 * 1e9)
        else:
            since = e.t_ns
        notes, ok = [], True
        for r in self.robots:
            # its speed when the stop came, at most: the speed last heard before the order, plus what
            # its joints' acceleration could add since (a hogged run's arm stood 2 ms past a bound
            # taken from a 10 ms old speed); and at most the first speed heard after the order plus
            # what they could have shed by then.  The bus killed, the last truth before the order
            # was 1.2 s old: capped at a truth period, as it was, the bound took an arm that had
            # sped up meanwhile for one slow to stop (kill:bus on XDP, 2 of 3 rounds, 117 ms
            # against 91-97)
            before = self.obs.between(r, since - 500_000_000, since) or self.obs.between(r, 0, since)
            samples = self.obs.between(r, since, t_resume)
            a = self.braking(r)
            top = before[-1][1] + a * (since - before[-1][0]) / 1e9 if before else float("inf")
            if samples:
                top = min(top, samples[0][1] + a * (samples[0][0] - since) / 1e9)
            top = min(top, float(np.max(models.get(self.config.robot(r).model).v_max)))  # (its joints' top)
            bound = self.estop_bound_ms(r, top) + e.stolen_ms
            moving = [t for t, qd, _, _ in samples if qd >= REST]
            by_truth = (max(moving) - since) / 1e6 if moving else 0.0
            heard = bool(samples) and samples[-1][0] - since > bound * 1e6
            reported = e.still_ms.get(r) if through else None
            good = by_truth <= bound and (heard or (reported is not None and reported <= bound + REPORT_MS))
            ok = ok and good
            told = "no report" if reported is None else f"reported still {reported:.0f} ms"
            truth = f"truth moving until {by_truth:.0f} ms" if heard else "no truth heard"
            stolen = f", {e.stolen_ms:.0f} of them stolen" if e.stolen_ms else ""
            notes.append(f"{r}: {truth}, {told} (bound {bound:.0f} ms{stolen})")
        how = "by the order" if since == e.t_ns else "by the link's watchdog (the hub down)"
        return ok, f"{how}: " + "; ".join(notes) + (f"; {e.error}" if e.error else "")

    def _q_near(self, robot: str, t_ns: int) -> np.ndarray:
        """The robot's joints at the last truth sample before t_ns."""
        before = self.obs.between(robot, 0, t_ns)
        return before[-1][2] if before else np.full(6, np.nan)

    def _status_held(
        self,
        fault: Fault,
        st: health_pb2.CellStatus | None,
        restarts_before: dict[str, int],
        stale_seen: set[str],
    ) -> tuple[bool, str]:
        if st is None:
            last = self.last_status
            sick = (
                [f"{s.name} {s.health}" for s in last.services if s.health != Health.OK] if last else ["none"]
            )
            rest = [self.obs.describe(r) for r in self.robots if not self.obs.at_rest(r)]
            return False, f"the cell did not come back to health: {sick}, not at rest: {rest}"
        by = {s.name: s for s in st.services}
        notes, ok = [], True
        for a in fault.actions:
            s = by.get(a.target)
            if s is None:
                continue
            if isinstance(a, Kill):
                grew = s.last.restarts - restarts_before.get(a.target, 0)
                good = grew >= 1 and bool(s.last.last_error) and s.health == Health.OK
                notes.append(
                    f"{a.target}: restarts +{grew} (pid {s.last.pid}), last error {s.last.last_error!r}"
                )
            elif isinstance(a, Hang) and a.target == "bus":  # status goes over the bus: none comes
                good = "bus" in stale_seen and s.health == Health.OK
                notes.append("bus: status unavailable while it hung" if good else "bus: status answered?")
            elif isinstance(a, Hang):
                good = a.target in stale_seen and s.health == Health.OK
                notes.append(f"{a.target}: {'stale seen' if a.target in stale_seen else 'never seen stale'}")
            else:
                continue
            ok = ok and good
        return ok, "; ".join(notes)


def _counters(st: health_pb2.CellStatus | None) -> dict[str, float]:
    if st is None:
        return {}
    return {f"{s.name}.{k}": v for s in st.services for k, v in s.last.counters.items()}


def _grew(before: dict[str, float], after: dict[str, float], keys: tuple[str, ...]) -> dict[str, float]:
    """How much each of these counters grew (those that changed)."""
    return {
        k: after.get(k, 0.0) - before.get(k, 0.0) for k in keys if after.get(k, 0.0) != before.get(k, 0.0)
    }


def _cell_overrides(link_pub: str, link_sub: str, config_path: str | None = None) -> dict[str, Any]:
    """The default cell (with config_path's settings over it), one process per service, its controller
    behind the campaign's link."""
    base = load_config(config_path)
    groups = [asdict(g) for g in base.services.groups]
    groups.append(
        {"name": "remote-controller", "services": ["controller"], "bus_pub": link_pub, "bus_sub": link_sub}
    )
    robots = default_robots()
    # and a UR arm reached only through the daemon (its controller emulated here): the daemon under the
    # same faults, and its controller going away
    ur = {"id": max(r["id"] for r in robots) + 1, "skill_port": free_port(), "backend": "ur",
          "ur_emulate": "mujoco", "truth_hz": robots[-1]["truth_hz"]}  # fmt: skip
    robots.append({**ur, "name": f"r{ur['id']}"})
    return {"services": {"layout": "each", "groups": groups}, "robots": robots}


async def campaign(
    rounds: int = 1, only: list[str] | None = None, log_fn=print, config_path: str | None = None
) -> dict[str, Any]:
    """Run the campaign; the figures (faults, held, failed, per fault) as a dict.  config_path: a
    cell config whose settings go under the campaign's own (its bus, robots and layout)."""
    bus_pub, bus_sub = f"tcp://127.0.0.1:{free_port()}", f"tcp://127.0.0.1:{free_port()}"
    link_pub, link_sub = f"tcp://127.0.0.1:{free_port()}", f"tcp://127.0.0.1:{free_port()}"
    user = tomllib.loads(await asyncio.to_thread(Path(config_path).read_text)) if config_path else {}
    overrides = {
        **user,
        "bus": {**user.get("bus", {}), "pub": bus_pub, "sub": bus_sub},
        **_cell_overrides(link_pub, link_sub, config_path),
    }
    base_bus = load_config(None).bus
    link = DelayLink(replace(base_bus, pub=bus_pub, sub=bus_sub), link_pub, link_sub, 0.0, 0.0, seed=1)
    results: list[FaultResult] = []
    async with asyncio.TaskGroup() as tg:
        link_task = tg.create_task(link.run(), name="controller-link")
        try:
            async with running_cell(overrides) as config, Bus.connect(config.bus, "chaos", wait=False) as bus:
                obs = Observer(bus, [r.name for r in config.robots])
                watch = tg.create_task(obs.run(), name="observer")
                try:
                    camp = Campaign(config, link, obs)
                    ur = tuple(r.name for r in config.robots if r.backend == "ur")
                    in_kernel = config.dataplane.runs.in_kernel
                    faults = catalogue(camp.robots, ur_robots=ur, in_kernel=in_kernel)
                    if only:
                        faults = [f for f in faults if any(o in f.name for o in only)]
                    total = rounds * len(faults)
                    log_fn(
                        f"{len(faults)} faults x {rounds} round(s): about "
                        f"{total * FAULT_S / 60:.0f} min here (about {FAULT_S:.0f} s a fault)"
                    )
                    for k in range(rounds):
                        for i, f in enumerate(faults, 1):
                            r = await camp.run(f)
                            results.append(r)
                            log_fn(f"[{k * len(faults) + i}/{total}] " + _row(k + 1, r))
                finally:
                    watch.cancel()
        finally:
            link_task.cancel()
    return summary(results, rounds)


def _row(round_no: int, r: FaultResult) -> str:
    failed = [k for k, v in r.held.items() if not v]
    det = "-" if r.detect_ms is None else f"{r.detect_ms:.0f} ms"
    rec = "-" if r.recover_s is None else f"{r.recover_s:.1f} s"
    why = "; ".join(f"{k}: {r.detail.get(k, '')}" for k in failed)
    return f"{round_no:>2} {r.name:<28} {'held' if r.ok else 'FAILED':<7} {det:>8} {rec:>8}  {why}"


def summary(results: list[FaultResult], rounds: int) -> dict[str, Any]:
    faults = len(results)
    held = sum(r.ok for r in results)
    per: dict[str, Any] = {}
    for r in results:
        e = per.setdefault(r.name, {"runs": 0, "held": 0, "detect_ms": [], "recover_s": [], "failed": []})
        e["runs"] += 1
        e["held"] += r.ok
        for k, v in r.figures.items():
            e[k] = round(max(e.get(k, 0.0), v), 2)
        if r.detect_ms is not None:
            e["detect_ms"].append(round(r.detect_ms, 1))
        if r.recover_s is not None:
            e["recover_s"].append(round(r.recover_s, 2))
        e["failed"] += [k for k, v in r.held.items() if not v]
    return {
        "faults": faults,
        "held": held,
        "failed": faults - held,
        "rounds": rounds,
        "promises": PROMISES,
        "per_fault": per,
        "host": socket.gethostname(),
    }
