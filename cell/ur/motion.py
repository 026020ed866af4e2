"""The motions a UR program makes, as joint-velocity commands for the arm's drives, one tick at a time.

URScript's moves are acceleration-limited (trapezoidal) profiles: `movej` moves every joint on one
profile so that they start and end together (the leading joint at a, v), `movel` moves the TCP along a
straight line (and its orientation about one axis) at a, v of the tool, `speedj`/`speedl` ramp to a
velocity at a and hold it, `servoj` follows a stream of joint targets, `stopj`/`stopl` decelerate at a.
Each is a reference in time; the drives are told the reference's velocity one tick ahead plus a
proportional pull on the position error (KP), so they end on the goal, not near it.

The TCP is the flange and the program's `set_tcp` offset (Tool); poses are UR's p[x, y, z, rx, ry, rz]
(m, rotation vector in rad) in the base frame.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import mujoco
import numpy as np

from cell.robot.arm import ArmModel
from cell.robot.kinematics import Kinematics, Unreachable
from cell.robot.pose import from_rotvec, rotation_error, slerp, to_rotvec

KP = 30.0  # 1/s: pull toward the reference position (a 33 ms time constant on what the feed-forward misses)
AT_GOAL_RAD = 2e-5  # a move has ended once every joint is this close to its goal (and so slower than
# KP * AT_GOAL_RAD < STEADY_RAD_S: is_steady() right after it is true)
STEADY_RAD_S = 1e-3  # is_steady(): every joint slower than this
SCALING_SAMPLES = 16  # points along a line or an arc where its joints' rates are found (MoveL._scaled)
SCALING_MARGIN = 0.9  # of each joint's velocity and acceleration limits a planned line may use
# servoj's lookahead is its loop's time constant here (closed in the robots' tick: Drives.servo):
# under 0.1 s that loop rang and grew on a 500 Hz stream when it closed on the arm's state a few ms
# late (URCL's default 0.03 s took a 0.1 rad sine to 0.34 rad), so shorter ones are held at 0.1 s
# (a UR's own loop is faster)
SERVO_LOOKAHEAD_MIN_S = 0.1
SETTLE_S = 2.0  # a move that cannot reach its goal (held by a stop) ends this long after its profile


def pull(err: np.ndarray, a_max: np.ndarray) -> np.ndarray:
    """The velocity that closes a position error: proportional (KP), but never faster than braking
    at 0.8 of the joints' acceleration limits would stop it on the spot (a gain alone overshoots,
    and rings, an arm that is acceleration-limited and far off)."""
    size = np.abs(err)
    return np.sign(err) * np.minimum(KP * size, np.sqrt(1.6 * a_max * size))


class Tool:
    """The arm's kinematics as URScript sees them: TCP poses through the flange and set_tcp's offset."""

    def __init__(self, arm: ArmModel) -> None:
        self.arm = arm
        self.kin = Kinematics(arm)
        self.tcp_pos, self.tcp_rot = np.zeros(3), np.eye(3)
        self.tcp = np.zeros(6)  # the offset as set_tcp was given it (RTDE's tcp_offset reports it so)
        self._jp, self._jr = np.zeros((3, arm.model.nv)), np.zeros((3, arm.model.nv))

    def set_tcp(self, pose: np.ndarray) -> None:
        self.tcp = np.asarray(pose[:6], np.float64).copy()
        self.tcp_pos, self.tcp_rot = self.tcp[:3].copy(), from_rotvec(self.tcp[3:])

    def frame(self, q: np.ndarray, tcp: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """The TCP's position and rotation matrix at q (with another offset if given)."""
        tp, tr = (self.tcp_pos, self.tcp_rot) if tcp is None else (np.asarray(tcp[:3]), from_rotvec(tcp[3:]))
        pos, rot = self.arm.fk(q)
        return pos + rot @ tp, rot @ tr

    def fk(self, q: np.ndarray, tcp: np.ndarray | None = None) -> np.ndarray:
        pos, rot = self.frame(q, tcp)
        return np.concatenate([pos, to_rotvec(rot)])

    def ik(self, pos: np.ndarray, rot: np.ndarray, near: np.ndarray) -> np.ndarray:
        """Joints putting the TCP at (pos, rot), nearest `near`; Unreachable if none."""
        flange_rot = rot @ self.tcp_rot.T
        return self.kin.ik(pos - flange_rot @ self.tcp_pos, flange_rot, near)

    def ik_pose(self, pose: np.ndarray, near: np.ndarray) -> np.ndarray:
        return self.ik(np.asarray(pose[:3], np.float64), from_rotvec(pose[3:]), near)

    def jacobian(self, q: np.ndarray) -> np.ndarray:
        """6 x dof: the TCP point's linear and the tool's angular velocity per joint velocity."""
        m, d = self.kin.model, self.kin.data
        d.qpos[:] = q
        mujoco.mj_kinematics(m, d)
        mujoco.mj_comPos(m, d)
        site = self.arm.tool_site  # (the TCP from this pass's flange: no second forward kinematics)
        pos = d.site_xpos[site] + d.site_xmat[site].reshape(3, 3) @ self.tcp_pos
        mujoco.mj_jac(m, d, self._jp, self._jr, pos, m.site_bodyid[site])
        return np.vstack([self._jp, self._jr])


@dataclass(frozen=True, slots=True)
class Trapezoid:
    """Distance along a path of `length` over time: accelerate at a, cruise at v, brake at a."""

    length: float
    v: float
    a: float
    ta: float  # accelerating (and braking) time
    tc: float  # cruising time

    @classmethod
    def make(cls, length: float, v: float, a: float) -> Trapezoid:
        v, a = max(v, 1e-9), max(a, 1e-9)
        if length <= 0:
            return cls(0.0, v, a, 0.0, 0.0)
        ta = v / a
        if a * ta * ta >= length:  # no cruise: a triangle
            ta = math.sqrt(length / a)
            return cls(length, a * ta, a, ta, 0.0)
        return cls(length, v, a, ta, (length - a * ta * ta) / v)

    @property
    def duration(self) -> float:
        return 2 * self.ta + self.tc

    def at(self, t: float) -> tuple[float, float]:
        """(distance, speed) at time t."""
        ta, tc, v, a = self.ta, self.tc, self.v, self.a
        if t <= 0:
            return 0.0, 0.0
        if t < ta:
            return 0.5 * a * t * t, a * t
        if t < ta + tc:
            return 0.5 * a * ta * ta + v * (t - ta), v
        if t < 2 * ta + tc:
            r = 2 * ta + tc - t
            return self.length - 0.5 * a * r * r, a * r
        return self.length, 0.0


class Motion:
    """A motion under way: step() gives the drives' velocity command for the next tick."""

    done = False
    error = ""  # why it ended without reaching its goal

    def step(self, q: np.ndarray, qd: np.ndarray, dt: float) -> np.ndarray:
        raise NotImplementedError

    def reference(self) -> tuple[np.ndarray, np.ndarray] | None:
        """Where the motion means the joints to be now, and how fast (None: no reference of its own)."""
        return None


class MoveJ(Motion):
    """movej: every joint on one trapezoid (the leading joint at a, v; none past its own limits)."""

    def __init__(self, q0: np.ndarray, goal: np.ndarray, v: float, a: float, arm: ArmModel) -> None:
        self.q0, self.goal = q0.copy(), np.asarray(goal, np.float64).copy()
        dq = self.goal - self.q0
        lead = float(np.abs(dq).max())
        self.dir = dq / lead if lead > 0 else np.zeros_like(dq)
        share = np.abs(self.dir)
        lim = arm.limits
        with np.errstate(divide="ignore"):
            v = min(v, float(np.min(np.where(share > 0, lim.v_max / share, np.inf))))
            a = min(a, float(np.min(np.where(share > 0, lim.a_max / share, np.inf))))
        self.profile = Trapezoid.make(lead, v, a)
        self.t = 0.0

    def step(self, q: np.ndarray, qd: np.ndarray, dt: float) -> np.ndarray:
        s_now, _ = self.profile.at(self.t)
        self.t += dt
        _, sd = self.profile.at(self.t)
        err = self.q0 + self.dir * s_now - q
        if self.t >= self.profile.duration:
            left = np.abs(self.goal - q).max()
            if left <= AT_GOAL_RAD or self.t > self.profile.duration + SETTLE_S:
                self.done = True
                self.error = "" if left <= AT_GOAL_RAD else f"ended {left:.2g} rad from its goal"
        return self.dir * sd + KP * err


class MoveL(Motion):
    """movel: the TCP on a straight line, its orientation turning about one axis, one trapezoid for both
    (the tool at a, v in m/s, m/s^2; a pure rotation at a, v in rad/s, rad/s^2)."""

    def __init__(self, q0: np.ndarray, goal: np.ndarray, v: float, a: float, tool: Tool) -> None:
        self.tool = tool
        self.p0, self.r0 = tool.frame(q0)
        self.p1, self.r1 = np.asarray(goal[:3], np.float64), from_rotvec(goal[3:])
        self.q_end = tool.ik(self.p1, self.r1, q0)  # (raises Unreachable before anything moves)
        length = float(np.linalg.norm(self.p1 - self.p0))
        turn = float(np.linalg.norm(rotation_error(self.r1, self.r0)))
        self.lead = length if length > 1e-6 else turn
        self.t = 0.0
        self.q_ref = q0.copy()
        self.profile = Trapezoid.make(self.lead, *self._scaled(q0, v, a))

    def _scaled(self, q0: np.ndarray, v: float, a: float) -> tuple[float, float]:
        """v and a, slowed where the line needs a joint faster than its limits (a UR's speed scaling,
        planned ahead): the joints' rate along the path, sampled, bounds the path's own."""
        if self.lead <= 0:
            return v, a
        near, rate = q0, np.zeros_like(q0)
        for s in np.linspace(0.0, 1.0, SCALING_SAMPLES + 1)[1:]:
            q = self._at(s, near)
            rate = np.maximum(rate, np.abs(q - near) * SCALING_SAMPLES / self.lead)  # rad per path unit
            near = q
        lim = self.tool.arm.limits
        with np.errstate(divide="ignore"):
            v_cap = float(np.min(np.where(rate > 0, SCALING_MARGIN * lim.v_max / rate, np.inf)))
            a_cap = float(np.min(np.where(rate > 0, SCALING_MARGIN * lim.a_max / rate, np.inf)))
        return min(v, v_cap), min(a, a_cap)

    def _at(self, s: float, near: np.ndarray) -> np.ndarray:
        """The joints at fraction s of the path."""
        return self.tool.ik(self.p0 + (self.p1 - self.p0) * s, slerp(self.r0, self.r1, s), near)

    def _ref(self, t: float, near: np.ndarray) -> np.ndarray:
        d, _ = self.profile.at(t)
        return self._at(d / self.lead if self.lead > 0 else 1.0, near)

    def step(self, q: np.ndarray, qd: np.ndarray, dt: float) -> np.ndarray:
        if self.t >= self.profile.duration:
            self.t += dt
            left = np.abs(self.q_end - q).max()
            if left <= AT_GOAL_RAD or self.t > self.profile.duration + SETTLE_S:
                self.done = True
                self.error = "" if left <= AT_GOAL_RAD else f"ended {left:.2g} rad from its goal"
            return pull(self.q_end - q, self.tool.arm.limits.a_max)
        now = self.q_ref
        self.t += dt
        try:
            self.q_ref = self._ref(self.t, now)
        except Unreachable as exc:
            self.done, self.error = True, f"the line leaves the arm's reach: {exc.reason}"
            return np.zeros_like(q)
        return (self.q_ref - now) / dt + KP * (now - q)


class MoveC(MoveL):
    """movec: the TCP on the circle through where it is, the via point and the target, one trapezoid
    along the arc (m/s, m/s^2); its orientation turning from the start's to the target's (mode 0,
    unconstrained) or kept (mode 1, fixed).  Three points on a line make a straight line."""

    def __init__(self, q0: np.ndarray, via: np.ndarray, goal: np.ndarray, v: float, a: float, tool: Tool,
                 fixed: bool = False) -> None:  # fmt: skip
        p0, _ = tool.frame(q0)
        pv, p1 = np.asarray(via[:3], np.float64), np.asarray(goal[:3], np.float64)
        d1, d2 = pv - p0, p1 - p0
        normal = np.cross(d1, d2)
        self.circle: tuple[np.ndarray, float, np.ndarray, np.ndarray, float] | None = None
        if float(np.linalg.norm(normal)) > 1e-9:
            center = p0 + np.cross(d1 @ d1 * d2 - d2 @ d2 * d1, normal) / (2 * normal @ normal)
            radius = float(np.linalg.norm(p0 - center))
            u = (p0 - center) / radius
            w = np.cross(normal / np.linalg.norm(normal), u)
            end = p1 - center
            sweep = math.atan2(float(end @ w), float(end @ u)) % (2 * math.pi)
            self.circle = (center, radius, u, w, sweep)
        target = np.concatenate([p1, to_rotvec(tool.frame(q0)[1]) if fixed else np.asarray(goal[3:])])
        super().__init__(q0, target, v, a, tool)
        if self.circle is not None:  # (the arc's length leads, not the chord's)
            self.lead = self.circle[1] * self.circle[4]
            self.profile = Trapezoid.make(self.lead, *self._scaled(q0, v, a))

    def _at(self, s: float, near: np.ndarray) -> np.ndarray:
        if self.circle is None:  # (three points on a line)
            return super()._at(s, near)
        center, radius, u, w, sweep = self.circle
        angle = sweep * s
        pos = center + radius * (math.cos(angle) * u + math.sin(angle) * w)
        return self.tool.ik(pos, slerp(self.r0, self.r1, s), near)


class _Ramp(Motion):
    """A velocity (of the joints or of the tool) ramped to a target, the leading change at a, and held."""

    def __init__(self, now: np.ndarray, target: np.ndarray, a: float) -> None:
        self.v = np.asarray(now, np.float64).copy()
        self.set(target, a)

    def set(self, target: np.ndarray, a: float) -> None:
        self.target, self.a = np.asarray(target, np.float64).copy(), max(a, 1e-9)

    def ramp(self, dt: float) -> np.ndarray:
        dv = self.target - self.v
        big = float(np.abs(dv).max())
        if big > self.a * dt:
            dv *= self.a * dt / big
        self.v = self.v + dv
        return self.v


class Speed(_Ramp):
    """speedj: ramp every joint's velocity to qd and hold it.  With qd zero and `stop` it is stopj: it
    ends once the arm stands."""

    def __init__(self, qd_now: np.ndarray, qd: np.ndarray, a: float, stop: bool = False) -> None:
        super().__init__(qd_now, qd, a)
        self.stop = stop

    def step(self, q: np.ndarray, qd: np.ndarray, dt: float) -> np.ndarray:
        v = self.ramp(dt)
        if self.stop and not v.any() and float(np.abs(qd).max()) < STEADY_RAD_S:
            self.done = True
        return v


class SpeedL(_Ramp):
    """speedl: ramp the tool's velocity (linear m/s, angular rad/s, base frame) to xd and hold it."""

    def __init__(self, tool: Tool, q: np.ndarray, qd: np.ndarray, xd: np.ndarray, a: float) -> None:
        super().__init__(tool.jacobian(q) @ qd, xd, a)
        self.tool = tool

    def step(self, q: np.ndarray, qd: np.ndarray, dt: float) -> np.ndarray:
        x = self.ramp(dt)
        jac = self.tool.jacobian(q)
        return jac.T @ np.linalg.solve(jac @ jac.T + 1e-6 * np.eye(6), x)


class Servo(Motion):
    """servoj: follow a stream of joint targets.  Each target's step over its time t is fed forward and
    the rest pulled in with the lookahead time as time constant; with no new target the arm settles on
    the last one.  (UR's gain is taken and not modelled.)"""

    def __init__(self, q: np.ndarray, extrapolates: bool = False) -> None:
        self.target = q.copy()
        self.ff = np.zeros_like(q)
        self.t, self.lookahead, self.since = 0.002, 0.1, 0.0
        self.extrapolates = extrapolates  # with no new target the last one moves on (URCL's script)
        # a reference the drives have not been given (the arm hands it to Drives.set_servo, whose
        # loop runs in the tick: this one runs when the program does, which may be ticks late)
        self.fresh = True

    def set(self, target: np.ndarray, t: float, lookahead: float) -> None:
        target = np.asarray(target, np.float64)
        if not (np.isfinite(target).all() and math.isfinite(t) and math.isfinite(lookahead)):
            # (a client's NaN would reach the drives' loop, every tick, and the arm's state with it)
            why = f"servoj(): not a number in q {target.tolist()}, t {t} or lookahead {lookahead}"
            raise Unreachable(why)
        t, lookahead = min(max(t, 0.002), 1.0), min(max(lookahead, SERVO_LOOKAHEAD_MIN_S), 0.2)
        # (the same target again is no news: the drives' feed-forward runs out on its own; given it,
        # a program catching up on ticks would cut the last step's feed-forward short)
        same = np.array_equal(target, self.target) and (t, lookahead) == (self.t, self.lookahead)
        self.fresh |= not same
        self.t = t
        self.ff = (target - self.target) / self.t
        self.target = target.copy()
        self.lookahead = lookahead
        self.since = 0.0

    def extrapolate(self, dt: float) -> None:
        """No new target this cycle: the last one moves on at its speed (the drives do the same)."""
        fresh = self.fresh
        self.set(self.target + self.ff * dt, dt, self.lookahead)
        self.fresh = fresh

    def step(self, q: np.ndarray, qd: np.ndarray, dt: float) -> np.ndarray:
        self.since += dt
        ff = self.ff if self.since <= self.t + 1e-9 else 0.0
        return ff + (self.target - q) / self.lookahead
