"""`cell bench accuracy`: how closely MuJoCo-simulated arms follow what the controller planned.

A real cell (bus, data plane, two MuJoCo arms publishing ground truth at 500
Hz) runs in a child process; the controller runs here and drives reference
motions through the data plane.  Measured from ground truth:

- stop error: after each motion, |q - goal| once the robot has held on its
  last TP for SETTLE_S (rad, the largest joint);
- path error: the tool position at every TP's time against the plan's tool
  position at that time (mm), for joint moves and straight-line moves;
- sync shift: how far apart two robots started together begin to move
  (ms), for a shared start time, a merged entity, and, as the baseline,
  two robots started one after the other (what independent controllers do).
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np

from cell.bench.registry import Bench, Figures, log, register
from cell.bus import Bus
from cell.cellproc import robots_heard, running_cell
from cell.config import DATAPLANE_BACKENDS
from cell.controller.controller import Controller, MotionStopped, Segment
from cell.ports import free_port as _port
from cell.robot.datagram import SCALE
from cell.robot.kinematics import Kinematics
from cell.robot.truth import Truth

SETTLE_S = 4.0  # held on the final TP this long before the stop error is read (1/K = 0.5 s)
EXPECTED_S = {True: 50, False: 170}  # the whole bench on this machine kind, --quick and not
Q0 = np.array([0.0, -1.5708, 1.5708, -1.5708, -1.5708, 0.0])


def tool_errors_mm(kin: Kinematics, truth: Truth, name: str, seg: Segment, joints: slice) -> np.ndarray:
    """|tool(truth) - tool(plan)| at each TP's time (mm)."""
    t_tp = seg.start_ns + seg.sections.t_end * 1e9
    q_real = truth.at(name, t_tp)
    q_plan = seg.sections.q[:, joints]
    return np.array(
        [np.linalg.norm(kin.fk(a)[0] - kin.fk(b)[0]) * 1000 for a, b in zip(q_real, q_plan, strict=True)]
    )


@dataclass
class Samples:
    """The raw figures, for plots (cell bench paper); not part of the JSON line."""

    path_joint_mm: list[list[float]]  # each joint move's tool error at its TPs
    path_linear_mm: list[list[float]]  # each straight line's
    stop_rad: list[float]  # each stop's largest joint error at rest
    switch_rad: list[float]  # each switch's start-state error, ours
    switch_paper_rad: list[float]  # the same, with Sec. 6.1's binned predictor
    shift_ms: dict[str, list[float]]  # start shifts between the two robots, by way of starting


@dataclass
class Accuracy:
    """What `cell bench accuracy` measured (NSDI'22 Secs. 6.1, 7.2-7.4)."""

    stop_error_rad_max: float
    path_error_mm_max: float
    path_error_mm_median: float
    path_error_mm_max_joint: float
    path_error_mm_max_linear: float
    switch_error_rad_max: float
    switch_error_paper_rad_max: float
    sync_shift_ms_max: float
    sync_shift_ms_shared: float
    sync_shift_ms_merged: float
    sync_shift_ms_independent: float
    sync_shift_ms_switch: float
    settle_s: float
    quick: bool
    samples: Samples = field(repr=False)
    backend: str = "numpy"
    seconds: float = 0.0

    def to_json(self) -> dict[str, Any]:
        """The JSON line: every figure but the samples (they are for the paper's plots)."""
        out = asdict(self)
        out.pop("samples")
        return out


async def measure(quick: bool, log: Callable[[str], None], backend: str = "numpy") -> Accuracy:
    robots = [
        {"id": i, "name": f"r{i}", "skill_port": _port(), "backend": "mujoco", "truth_hz": 500}
        for i in (1, 2)
    ]
    overrides: dict[str, Any] = {"robots": robots, "services": {"run": ["bus", "dataplane", "robots"]}}
    if DATAPLANE_BACKENDS[backend].in_kernel:  # the data plane in a switch namespace of this run's own
        from cell.bench.xdpnet import xdp_dataplane, xdp_switch

        overrides["dataplane"] = xdp_dataplane(xdp_switch(tag="cba"))
    kin = Kinematics()
    stop_err: list[float] = []
    path_joint: list[np.ndarray] = []
    path_linear: list[np.ndarray] = []
    shifts: dict[str, list[float]] = {"shared": [], "merged": [], "independent": [], "switch": []}
    jumps: list[float] = []
    paper_pred: list[float] = []  # the same switches, start state as Sec. 6.1 of the paper predicts it
    log(
        f"joint moves, straight lines, re-plans and synchronised starts on two MuJoCo arms: about "
        f"{EXPECTED_S[quick]} s here (a line per move as it ends)"
    )
    async with (
        running_cell(overrides) as config,
        Bus.connect(config.bus, "bench-accuracy") as bus,
        Truth.watching(bus) as truth,
        Controller(bus, config) as ctl,
    ):
        await robots_heard(ctl, {1, 2})

        async def settle_and_read(name: str, goal: np.ndarray, end_ns: int) -> None:
            await truth.until(name, end_ns + int(SETTLE_S * 1e9))
            q = truth.at(name, np.array([end_ns + SETTLE_S * 1e9]))[0]
            stop_err.append(float(np.abs(q - goal).max()))

        # joint moves, each from where the last ended
        rng = np.random.default_rng(7)
        n_joint = 2 if quick else 5
        for i in range(n_joint):
            goal = Q0 + rng.uniform(-0.6, 0.6, 6)
            res = await ctl.move_joints("r1", goal, speed=0.6)
            seg = ctl.track("r1").segment
            assert seg is not None  # (the move it planned)
            path_joint.append(tool_errors_mm(kin, truth, "r1", seg, slice(0, 6)))
            await settle_and_read("r1", goal, res.end_ns)
            log(
                f"joint move {i + 1}: path error at TPs max {path_joint[-1].max():.2f} mm "
                f"(TP {int(path_joint[-1].argmax()) + 1} of {path_joint[-1].size}), "
                f"stop error {stop_err[-1]:.1e} rad"
            )
        await ctl.move_joints("r1", Q0, speed=0.6)
        # straight lines: a square of 200 mm, tool pointing down, and a diagonal down and back
        pos0, rot0 = kin.fk(Q0)
        legs: list[tuple[float, float, float]] = [(0.2, 0, 0), (0, 0.2, 0), (-0.2, 0, 0), (0, -0.2, 0)]
        if not quick:
            legs += [(0.1, 0.1, -0.15), (-0.1, -0.1, 0.15)]
        pos = pos0.copy()
        for i, leg in enumerate(legs):
            pos = pos + np.array(leg)
            res = await ctl.move_linear("r1", pos, rot0, speed=1.0)
            seg = ctl.track("r1").segment
            assert seg is not None  # (the move it planned)
            path_linear.append(tool_errors_mm(kin, truth, "r1", seg, slice(0, 6)))
            e = path_linear[-1]
            log(
                f"linear move {i + 1}: path error at TPs max {e.max():.2f} mm "
                f"(TP {int(e.argmax()) + 1} of {e.size}), median {np.median(e):.2f} mm"
            )
        hold = ctl.track("r1").q_hold
        assert hold is not None
        await settle_and_read("r1", hold, res.end_ns)
        log(f"after the lines: stop error {stop_err[-1]:.1e} rad")
        # re-planning on the fly: branch off a long motion to another goal
        for k in range(2 if quick else 6):
            far = Q0 + np.array([1.0, -0.4, 0.3, 0.2, 0.0, 0.5]) * (1 if k % 2 == 0 else -1)
            first = asyncio.ensure_future(ctl.move_joints("r1", far, speed=0.4))
            await asyncio.sleep(0.6 + 0.2 * k)
            seg0 = ctl.track("r1").segment
            t_req = ctl.link.now()
            await ctl.replan("r1", Q0 + np.array([0.2, 0.2, -0.2, 0.0, 0.1, 0.0]), speed=0.6)
            with contextlib.suppress(MotionStopped):
                await first
            sw = ctl.engine.last_switch
            assert sw is not None and seg0 is not None
            q_real = truth.at("r1", np.array([sw.t_branch_ns]))[0]
            jumps.append(float(np.abs(q_real - sw.q_pred).max()))
            paper_pred.append(
                float(np.abs(q_real - paper_start(truth, "r1", seg0, t_req, sw.t_branch_ns)).max())
            )
            await ctl.move_joints("r1", Q0, speed=0.6)
        log(
            f"re-planning: {max(jumps) * 1000:.2f} mrad from the predicted start at the switch "
            f"(the paper's binned predictor: {max(paper_pred) * 1000:.2f} mrad)"
        )
        # synchronised starts
        await ctl.move_together({"r1": Q0, "r2": Q0}, speed=0.6)
        trials = 1 if quick else 3
        for k in range(trials):
            delta = np.array([0.3, -0.2, 0.2, 0.1, 0.1, 0.3]) * (1 if k % 2 == 0 else -1)
            here = {n: ctl.track(n).q_hold for n in ("r1", "r2")}
            res = await ctl.move_together({n: q + delta for n, q in here.items()}, speed=0.6)
            t1, t2 = (truth.start_of_motion(n, res.start_ns - 10_000_000) for n in ("r1", "r2"))
            shifts["shared"].append(abs(t1 - t2) / 1e6)
            # independently: one request after the other (each answered once its motion is
            # loaded and started), as two controllers would send them
            here = {n: ctl.track(n).q_hold for n in ("r1", "r2")}
            t_req = ctl.link.now()
            for n, q in here.items():
                await ctl.move_joints(n, q - delta, speed=0.6, wait=False)
            for n in here:
                await ctl.wait_idle(ctl.track(n))
            t1, t2 = (truth.start_of_motion(n, t_req) for n in ("r1", "r2"))
            shifts["independent"].append(abs(t1 - t2) / 1e6)
        # independent robots started by two pre-planned switch entries (Sec. 7.2): armed, then
        # fired by one update
        for k in range(3 if quick else 20):
            delta = np.array([0.3, -0.2, 0.2, 0.1, 0.1, 0.3]) * (1 if k % 2 == 0 else -1)
            here = {n: ctl.track(n).q_hold for n in ("r1", "r2")}
            armed = await ctl.arm({n: q + delta for n, q in here.items()}, speed=0.6)
            res = await ctl.fire(armed)
            t1, t2 = (truth.start_of_motion(n, res.start_ns - 10_000_000) for n in ("r1", "r2"))
            shifts["switch"].append(abs(t1 - t2) / 1e6)
        merged = await ctl.merge(["r1", "r2"])
        for k in range(3 if quick else 20):
            delta = np.array([0.3, -0.2, 0.2, 0.1, 0.1, 0.3]) * (1 if k % 2 == 0 else -1)
            here_q = merged.q_hold
            assert here_q is not None
            res = await ctl.move_joints("r1", here_q + np.tile(delta, 2), speed=0.6)
            t1, t2 = (truth.start_of_motion(n, res.start_ns - 10_000_000) for n in ("r1", "r2"))
            shifts["merged"].append(abs(t1 - t2) / 1e6)
        log(
            "start shift between two robots (ms): shared start "
            f"{max(shifts['shared']):.2f}, merged {max(shifts['merged']):.2f}, "
            f"two switch entries {max(shifts['switch']):.2f}, "
            f"one after the other {max(shifts['independent']):.2f}"
        )
    joint_all = np.concatenate(path_joint)
    linear_all = np.concatenate(path_linear)
    both = np.concatenate([joint_all, linear_all])
    return Accuracy(
        stop_error_rad_max=max(stop_err),
        path_error_mm_max=float(both.max()),
        path_error_mm_median=float(np.median(both)),
        path_error_mm_max_joint=float(joint_all.max()),
        path_error_mm_max_linear=float(linear_all.max()),
        switch_error_rad_max=max(jumps),
        switch_error_paper_rad_max=max(paper_pred),
        sync_shift_ms_max=max(max(shifts["shared"]), max(shifts["merged"])),
        sync_shift_ms_shared=max(shifts["shared"]),
        sync_shift_ms_merged=max(shifts["merged"]),
        sync_shift_ms_independent=max(shifts["independent"]),
        sync_shift_ms_switch=max(shifts["switch"]),
        settle_s=SETTLE_S,
        quick=quick,
        samples=Samples(
            [a.tolist() for a in path_joint],
            [a.tolist() for a in path_linear],
            stop_err,
            jumps,
            paper_pred,
            shifts,
        ),
        backend=backend,
    )


def granularity(p: np.ndarray, n_bits: int) -> np.ndarray:
    """g(p): the step the data plane's ternary tables resolve a fixed-point value p with when
    they keep n_bits significant bits (Sec. 5.3's M_rel = 2^-(n_bits-1)), in rad."""
    y = np.abs(np.rint(np.asarray(p) * SCALE)).astype(np.int64)
    b = np.floor(np.log2(np.maximum(y, 1))).astype(np.int64) + 1
    return np.exp2(np.maximum(b - n_bits, 0)) / SCALE


def paper_start(
    truth: Truth, name: str, seg: Segment, t_ns: int, t_switch_ns: int, n_bits: int = 8
) -> np.ndarray:
    """p_start of Sec. 6.1: the plan at t + dt, corrected by the status's position and velocity
    errors at t (read at t, when the re-plan was asked for), binned to the tables' granularity."""
    dt = (t_switch_ns - t_ns) / 1e9
    t_rel = np.array([(t_ns - seg.start_ns) / 1e9, (t_switch_ns - seg.start_ns) / 1e9])
    q_traj, v_traj = seg.motion.sample(t_rel)
    p_status = truth.at(name, np.array([t_ns]))[0]
    v_status = (p_status - truth.at(name, np.array([t_ns - 4_000_000]))[0]) / 0.004
    p_predict = q_traj[1] + p_status - q_traj[0] + (v_status - v_traj[0]) * dt
    g = granularity(p_predict, n_bits)
    return np.floor(p_predict / g) * g


def run(quick: bool, log: Callable[[str], None] = print, backend: str = "numpy") -> Accuracy:
    t0 = time.monotonic()
    result = asyncio.run(measure(quick, log, backend))
    result.seconds = round(time.monotonic() - t0, 1)
    return result


def format_result(r: Accuracy) -> str:
    """The figures, each with the NSDI'22 paper's beside it (Secs. 6.1, 7.2-7.4)."""
    return "\n".join(
        [
            f"stop error (held {r.settle_s:.0f} s on the last TP): max {r.stop_error_rad_max:.1e} rad "
            "(paper: ~0.5e-7 rad)",
            f"tool path error at TPs: max {r.path_error_mm_max:.2f} mm, "
            f"median {r.path_error_mm_median:.2f} mm (joint moves max {r.path_error_mm_max_joint:.2f}, "
            f"lines max {r.path_error_mm_max_linear:.2f}) (paper: 3.2 / 2.23 mm in-network, "
            "0.1 / 0.04 mm with ROS's PID)",
            f"re-planning: at the switch the robot was {r.switch_error_rad_max * 1000:.2f} mrad from the "
            "predicted start state (the jump the new branch has to absorb); the paper's binned "
            f"predictor (Sec. 6.1) {r.switch_error_paper_rad_max * 1000:.2f} mrad",
            f"start shift: shared start {r.sync_shift_ms_shared:.2f} ms, "
            f"merged {r.sync_shift_ms_merged:.2f} ms, "
            f"started one after the other {r.sync_shift_ms_independent:.2f} ms "
            "(paper: 0 merged, up to 8 ms started apart)",
            f"({r.seconds} s)",
        ]
    )


def _arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--quick", action="store_true", help="fewer reference motions (under 4 minutes)")
    p.add_argument("--backend", choices=["numpy", "xdp"], default="numpy", help="the data plane (xdp: root)")


def _main(args: argparse.Namespace) -> Figures:
    result = run(args.quick, log=log, backend=args.backend)
    return Figures(result, format_result(result))


register(
    Bench(
        "accuracy",
        "MuJoCo arms driven through the data plane: stop error, tool path error, start shift",
        _arguments,
        _main,
    )
)
