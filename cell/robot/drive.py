"""Velocity-mode joint drives with the robot's command-window semantics, vectorised over joints.

As in the in-network control design, each joint waits for commands during a
command window; of several, only the latest is kept, and it is executed at
the end of the window.  A robot whose joints get no command for `watchdog`
windows makes a protective stop (decelerates to 0 within its limits) and
resumes once every joint is commanded again.  The watchdog arms with a robot's
first command: a robot nobody has commanded yet simply stands still.  The
drive never exceeds the
joint's velocity or acceleration limit, whatever it is told.  A URScript program's servoj (cell.ur)
is a servo reference the drives close on the arm's position every tick (`servo`), as a UR's
controller does in its own real-time loop: the program, which runs at the normal policy and may be
late, only gives them the targets.  A halted robot
(an emergency stop on the Responsive Link) brakes at once with its full
deceleration and ignores every command until every holder (the e-stop, the arm's UR
state) has released it.
"""

from __future__ import annotations

import contextlib

import numpy as np

WATCHDOG_WINDOWS = 3


HOLD_ESTOP = 1  # the Responsive Link's e-stop (cell.robot.node)
HOLD_UR = 2  # the arm's UR state: powered off, braked, safety-stopped (cell.ur)


class _Count:
    """One of Drives.counts, read and set as an int."""

    def __init__(self, index: int) -> None:
        self.index = index

    def __get__(self, drives: Drives, owner: type) -> int:
        return int(drives.counts[self.index])

    def __set__(self, drives: Drives, value: int) -> None:
        drives.counts[self.index] = value


class Drives:
    """`robots` robots of `dof` joints each; arrays are (robots, dof)."""

    def __init__(self, robots: int, v_max: np.ndarray, a_max: np.ndarray, watchdog: int = WATCHDOG_WINDOWS):
        self.dof = len(v_max)
        shape = (robots, self.dof)
        self.v_max = np.broadcast_to(np.asarray(v_max, np.float64), shape).copy()
        self.a_max = np.broadcast_to(np.asarray(a_max, np.float64), shape).copy()
        self.watchdog = watchdog
        self.velocity = np.zeros(shape)  # what the drive is doing now (its velocity reference)
        self.target = np.zeros(shape)  # the command executing in this window
        self.pending = np.zeros(shape)  # the latest command received in this window
        self.has_pending = np.zeros(shape, bool)
        self.missed = np.zeros(shape, np.int64)  # windows in a row without a command, per joint
        self.stopped = np.zeros(robots, bool)  # protective stop
        self.armed = np.zeros(robots, bool)  # commanded at least once: the watchdog is on
        # who holds each robot halted (braking or standing, deaf to commands), a bit each (HOLD_*):
        # one holder letting go leaves it halted while another still holds it (an e-stop outlasts a
        # UR dashboard's brake release)
        self.holds = np.zeros(robots, np.uint8)
        # robots a URScript program drives (cell.ur): the datagram commands are not theirs (each one is
        # counted in `ignored`), no watchdog runs, and the program sets `target` itself every tick
        self.scripted = np.zeros(robots, bool)
        # servoj's reference, a robot's: its target position, the target's step fed forward as a speed
        # for `servo_t` seconds after it came (`servo_since` ago), the rest pulled in with time constant
        # `servo_tau` (0: no servo); with `servo_extrapolate` the target moves on at that speed until
        # the next one (URCL's extrapolate())
        self.servo_q = np.zeros(shape)
        self.servo_ff = np.zeros(shape)
        self.servo_t = np.zeros(robots)
        self.servo_since = np.zeros(robots)
        self.servo_tau = np.zeros(robots)
        self.servo_extrapolate = np.zeros(robots, bool)
        # commands ignored (scripted robots'), protective stops and windows so far: an array, so that
        # the tick in C (cell/robot/tick.c) counts them where Python reads them
        self.counts = np.zeros(3, np.int64)
        # held while halt(), script() and set_target() change the arrays: a tick in another thread
        # (cell/robot/tick.c's) never sees half of a change
        self.lock: contextlib.AbstractContextManager = contextlib.nullcontext()

    # every array above is updated in place, never rebound: the C tick holds their addresses
    ignored = _Count(0)
    stops = _Count(1)
    windows = _Count(2)

    def command(self, robot: np.ndarray, joint: np.ndarray, velocity: np.ndarray) -> None:
        """Commands received in this window, in arrival order: the latest per joint wins."""
        if robot.size == 0:
            return
        if self.scripted.any():
            mine = ~self.scripted[robot]
            self.ignored += int(robot.size - mine.sum())
            robot, joint, velocity = robot[mine], joint[mine], velocity[mine]
            if robot.size == 0:
                return
        flat = robot * self.dof + joint
        # np assignment gives no order guarantee for repeated indices: keep each joint's last one
        last = flat.size - 1 - np.unique(flat[::-1], return_index=True)[1]
        self.pending.flat[flat[last]] = velocity[last]
        self.has_pending.flat[flat[last]] = True

    @property
    def halted(self) -> np.ndarray:
        return self.holds != 0

    def halt(self, rows: np.ndarray, on: bool = True, by: int = HOLD_ESTOP) -> None:
        """Halt (brake now, ignore commands) or release these robots for holder `by`; released, they
        stand until commanded (their watchdog re-arms with the next command), halted still while
        another holder holds them."""
        bit = np.uint8(by)
        with self.lock:
            if on:
                self.holds[rows] |= bit
            else:
                self.holds[rows] &= ~bit
            self._clear(rows, rearm=not on)

    def script(self, row: int, on: bool) -> None:
        """A URScript program takes the robot over (on) or gives it back to the datagram program: it
        stands where it is until commanded, its watchdog re-armed by the next command."""
        with self.lock:
            self.scripted[row] = on
            self._clear(row, rearm=True)
            self.stopped[row] = False

    def set_target(self, row: int, velocity: np.ndarray | float) -> None:
        """What a URScript program drives robot `row` at in this period (cell.ur); its servo is off."""
        with self.lock:
            self.target[row] = velocity
            self.servo_tau[row] = 0.0

    def set_servo(
        self, row: int, q: np.ndarray, ff: np.ndarray, t: float, tau: float, extrapolate: bool = False
    ) -> None:
        """A URScript program's new servoj target for robot `row`: from the next tick the drives feed
        `ff` forward for `t` seconds and pull the rest in with time constant `tau` (see `servo`)."""
        with self.lock:
            self.servo_q[row], self.servo_ff[row] = q, ff
            self.servo_t[row], self.servo_since[row], self.servo_tau[row] = t, 0.0, tau
            self.servo_extrapolate[row] = extrapolate

    def servo(self, q: np.ndarray, dt: float) -> None:
        """The servoing robots' targets for the next dt, closed on their positions `q` now (motion.Servo's
        law, here so that it runs in the tick whenever the program that set it runs)."""
        on = self.servo_tau > 0.0
        if not on.any():
            return
        for r in np.flatnonzero(on & ~self.halted).tolist():  # (a robot or two: a program each)
            since = self.servo_since[r] + dt
            self.servo_since[r] = since
            ff = self.servo_ff[r]
            if since > self.servo_t[r] + 1e-9:
                if self.servo_extrapolate[r]:
                    self.servo_q[r] += ff * dt
                else:
                    ff = 0.0
            self.target[r] = ff + (self.servo_q[r] - q[r]) / self.servo_tau[r]

    def _clear(self, rows: np.ndarray | int, rearm: bool) -> None:
        """No command executing or pending; with rearm, the watchdog off until the next command."""
        self.target[rows] = 0.0
        self.servo_tau[rows] = 0.0
        self.pending[rows] = 0.0
        self.has_pending[rows] = False
        if rearm:
            self.armed[rows] = False
            self.missed[rows] = 0

    def end_window(self) -> tuple[np.ndarray, np.ndarray]:
        """Execute the kept commands; return (robots that just stopped, robots that just resumed)."""
        self.windows += 1
        has = self.has_pending
        has[self.halted] = False
        self.target[has] = self.pending[has]
        self.missed[has] = 0
        self.missed[~has] += 1
        self.armed |= has.any(axis=1)
        starved = (self.missed >= self.watchdog).any(axis=1) & self.armed & ~self.halted
        fed = has.all(axis=1)
        stopping = starved & ~self.stopped
        resuming = self.stopped & fed
        self.stopped[:] = (self.stopped | stopping) & ~resuming
        self.stops += int(stopping.sum())
        self.target[self.stopped | self.halted] = 0.0
        has[:] = False
        return np.flatnonzero(stopping), np.flatnonzero(resuming)

    def step(self, dt: float) -> np.ndarray:
        """Advance the drives by dt toward their targets within limits; return the mean velocity over dt."""
        # ufuncs, not np.clip: its Python wrapper costs more than the work at this size, every tick
        goal = np.minimum(np.maximum(self.target, -self.v_max), self.v_max)
        step = self.a_max * dt
        dv = np.minimum(np.maximum(goal - self.velocity, -step), step)
        before = self.velocity.copy()
        self.velocity += dv
        return before + 0.5 * dv
