"""The closed loop without sockets or clocks: the data plane's controller against a host PID.

One arm (MuJoCo, or the kinematic model) is stepped tick by tick with the
robot's own command semantics: a status every period, the answer to it in
hand by the next tick, the command kept from a window's last status acting
when the window ends.  Two controllers close the loop on the same motions:

- dataplane: the planner's TPs (cut and fitted as the controller does them,
  started on a window's first period) in the real Tables and Pipeline, which
  answer every status with v = (1-c1) v + c1 v_trg + c2 (p_trg - p);
- pid: a joint PID on the host, as the ROS driver's joint trajectory
  controller runs one (Sec. 7.4 of the paper's baseline): it has the whole
  plan, and answers every status with the plan's velocity one period ahead
  plus kp e + ki integral(e) + kd de/dt.

Both are judged as `cell bench accuracy` judges the live cell: the tool's
distance from the plan's tool position at each TP's time.  Exact timing (no
jitter, no missed ticks): what is left is the control law's own error.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from cell.config import load_config
from cell.controller.loop import LoopModel
from cell.controller.plan import Motion, MotionLimits, plan_joint
from cell.controller.tps import cut
from cell.dataplane.pipeline import ControlConstants, Pipeline
from cell.dataplane.tables import Tables, TPBatch
from cell.robot import datagram
from cell.robot.arm import arm_model
from cell.robot.backends import BACKENDS
from cell.robot.datagram import Kind
from cell.robot.kinematics import Kinematics

Q0 = np.array([0.0, -1.5708, 1.5708, -1.5708, -1.5708, 0.0])
PERIOD_NS = 2_000_000
WINDOW = 4
SETTLE_S = 1.0


@dataclass(frozen=True)
class Pid:
    """Gains of the host PID, the best of a scan over kp 10-40 /s, ki 0-100 /s^2, kd 0-0.02 s on
    reference_motions() (kp 40, ki 100: 0.10 mm max, 0.03 mm median at TPs on MuJoCo)."""

    kp: float = 40.0  # 1/s
    ki: float = 100.0  # 1/s^2
    kd: float = 0.0  # s


class Loop:
    """One arm and one controller, stepped a status period at a time."""

    def __init__(
        self, controller: str, backend: str = "mujoco", pid: Pid = Pid(), model: str | None = None
    ) -> None:
        cfg = load_config(None)
        dpc, cc = cfg.dataplane, cfg.controller
        arm = arm_model(model or cfg.robots[0].model)  # (default: the default cell's first robot's)
        lim = arm.limits
        self.limits = MotionLimits(
            v_max=np.minimum(lim.v_max, dpc.v_max),
            a_max=np.minimum(lim.a_max, cc.a_max),
            j_max=np.array(cc.j_max),
        )
        self.c1, self.c2 = np.array(dpc.c1), np.array(dpc.c2)
        self.loop = LoopModel(
            self.c1, self.c2, np.array(dpc.v_max), lim.a_max, PERIOD_NS / 1e9, WINDOW, dpc.n_bits
        )
        self.rate = cc.tp_rate_hz
        self.controller, self.pid = controller, pid
        self.sim = BACKENDS[backend](arm, Q0[None, :], 1_000_000)
        self.tables = Tables(capacity=4096)
        self.tables.add_robot(1, 6)
        constants = ControlConstants(tuple(dpc.c1), tuple(dpc.c2), dpc.n_bits, tuple(dpc.v_max))
        self.pipe = Pipeline(self.tables, constants)
        self.kin = Kinematics(arm)
        self.tick = 0
        self.inbox: np.ndarray | None = None
        self.next_id = 1
        self.integral = np.zeros(6)
        self.last_e = np.zeros(6)

    def now(self) -> int:
        return 1_000_000_000 + self.tick * PERIOD_NS

    def run(self, motion: Motion) -> np.ndarray:
        """Drive one motion from where the arm holds; the tool error at each TP's time (mm)."""
        # start on the first period of a window, two windows from now (as the controller does)
        k0 = -(-(self.tick + 2 * WINDOW) // WINDOW) * WINDOW
        start = 1_000_000_000 + k0 * PERIOD_NS
        secs = cut(motion, self.rate, self.c2 / self.c1, self.loop, tick0=0)
        if self.controller == "dataplane":
            self._load(motion, secs, start)
        t_tp = start + np.rint(secs.t_end * 1e9).astype(np.int64)
        end = int(t_tp[-1] + SETTLE_S * 1e9)
        ts, qs = [self.now()], [self.sim.q[0].copy()]
        while self.now() <= end:
            self._tick(motion, start)
            ts.append(self.now())  # (the state the step reached: the next period's)
            qs.append(self.sim.q[0].copy())
        q_hist = np.array(qs)
        q_real = np.stack([np.interp(t_tp, ts, q_hist[:, j]) for j in range(6)], axis=1)
        return np.array(
            [
                np.linalg.norm(self.kin.fk(a)[0] - self.kin.fk(b)[0]) * 1000
                for a, b in zip(q_real, secs.q, strict=True)
            ]
        )

    def _load(self, motion: Motion, secs, start: int) -> None:
        """The motion's TPs between a hold where it starts and a hold where it ends (velocity 0: the
        last section's fitted velocity would carry the arm on past its goal), as the controller
        loads them."""
        n = len(secs) + 2
        ids = np.arange(self.next_id, self.next_id + n)
        self.next_id += n
        q0 = motion.sample(np.array([0.0]))[0][0]
        pos = np.vstack([q0, secs.q if secs.p_trg is None else secs.p_trg, secs.q[-1:]])
        vel = np.vstack([np.zeros(6), secs.v_ff, np.zeros((1, 6))])
        dur = np.concatenate([[1.0], secs.duration, [1.0]])
        nxt = np.append(ids[1:], ids[-1])
        self.tables.insert(TPBatch(np.full(n, 1), ids, nxt, dur, np.full(n, 6), pos, vel))
        self.tables.set_registers(1, int(ids[0]), start - PERIOD_NS // 4)

    def _tick(self, motion: Motion, start: int) -> None:
        sim, drives = self.sim, self.sim.drives
        recs = datagram.empty(6)
        datagram.pack(recs, 1, np.arange(6), Kind.STATUS, self.tick + 1, sim.qd[0], sim.q[0])
        if self.inbox is not None:  # the answer to the last status, in hand by now
            drives.command(np.zeros(6, np.int64), np.arange(6), self.inbox)
        if self.tick % WINDOW == 0:
            drives.end_window()
        sim.step(PERIOD_NS / 1e9)
        if self.controller == "dataplane":
            self.pipe.process(recs, self.now())
            self.inbox = datagram.velocities(recs)
        else:
            self.inbox = self._pid(motion, start, datagram.velocities(recs), recs)
        self.tick += 1

    def _pid(self, motion: Motion, start: int, _v: np.ndarray, recs: np.ndarray) -> np.ndarray:
        """The host PID's answer to this status: the plan's velocity where the command will act
        (the next window's end at the latest: one period ahead) plus PID on the position error."""
        p = recs["position"].astype(np.float64) / datagram.SCALE
        t = (self.now() - start) / 1e9
        q_ref, _ = motion.sample(np.array([max(t, 0.0)]))
        _, v_ahead = motion.sample(np.array([max(t + PERIOD_NS / 1e9, 0.0)]))
        e = q_ref[0] - p
        dt = PERIOD_NS / 1e9
        self.integral = np.clip(self.integral + e * dt, -0.01, 0.01)
        d = (e - self.last_e) / dt
        self.last_e = e
        g = self.pid
        return v_ahead[0] + g.kp * e + g.ki * self.integral + g.kd * d


def reference_motions(limits: MotionLimits, n: int = 3, seed: int = 7, speed: float = 0.6) -> list[Motion]:
    """The accuracy bench's joint moves: random goals around Q0, each from where the last ended."""
    rng = np.random.default_rng(seed)
    out, q = [], Q0
    for _ in range(n):
        goal = Q0 + rng.uniform(-0.6, 0.6, 6)
        out.append(plan_joint(q, goal, limits.scaled(speed)))
        q = goal
    return out


def compare(n: int = 3, backend: str = "mujoco") -> dict[str, np.ndarray]:
    """Tool errors at TPs (mm) for each controller over the same n moves."""
    out = {}
    for controller in ("dataplane", "pid"):
        loop = Loop(controller, backend)
        errs = [loop.run(m) for m in reference_motions(loop.limits, n)]
        out[controller] = np.concatenate(errs)
    return out
