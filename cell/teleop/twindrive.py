"""The twin drive system (Responsive Processor paper, Sec. 4.2, Table 2, Figs. 11-13), in MuJoCo.

Two motors turn wheels that face each other; rollers pressed between them
carry the output axis, which therefore turns at half the difference of the
motors' speeds.  Both motors always spin (here at +/- BIAS around the
command), so their Coulomb friction never changes sign and never sticks: it
is a constant load each motor's servo carries, and at the output the two
cancel.  A usual drive is one such motor on the axis: below the speed at
which its servo's torque beats the Coulomb friction it stands still.

In MuJoCo each motor is a hinge with Table 2's inertia (armature), viscous
friction (damping) and Coulomb friction (frictionloss, MuJoCo's dry-friction
constraint, which holds the joint until the torque exceeds it).  The rollers
are a fixed tendon 1/2 m1 - 1/2 m2 - out held at zero by an equality
constraint.  Each motor has a speed servo (MuJoCo's velocity actuator).
Table 2's servo rigidity K_s is the stiffness of the drives' position
servo; a speed command has no position to hold, so what acts here is its
speed loop, whose gain is the damping of that servo made critical:
K_v = 2 sqrt(K_s J).
"""

from __future__ import annotations

from dataclasses import dataclass

import mujoco
import numpy as np

INERTIA = 2.965e-5  # kg m^2
VISCOUS = 2.240e-4  # N m s / rad (Table 2 prints N m / rad)
COULOMB = 1.527e-3  # N m
RIGIDITY = 544.4  # N m / rad
KV = 2.0 * np.sqrt(RIGIDITY * INERTIA)  # N m s / rad: the speed servo's gain
BIAS = 20.0  # rad/s: how fast both motors of the twin drive spin when the output stands still
TIMESTEP = 1e-4  # s
FRICTION_SOLREF = "0.0005 1"  # a stiff dry-friction constraint: no creep below the friction torque


def _motor(name: str, axis_x: float) -> str:
    return f"""
    <body name="{name}" pos="{axis_x} 0 0">
      <joint name="{name}" type="hinge" axis="0 0 1" armature="{INERTIA}" damping="{VISCOUS}"
             frictionloss="{COULOMB}" solreffriction="{FRICTION_SOLREF}"
             solimpfriction="0.9999 0.9999 0.001"/>
      <geom type="cylinder" size="0.02 0.005" mass="1e-6"/>
    </body>"""


def usual_xml() -> str:
    return f"""
<mujoco model="usual-drive">
  <option timestep="{TIMESTEP}" gravity="0 0 0"/>
  <worldbody>{_motor("out", 0)}
  </worldbody>
  <actuator><velocity name="m" joint="out" kv="{KV}"/></actuator>
</mujoco>"""


def twin_xml() -> str:
    return f"""
<mujoco model="twin-drive">
  <option timestep="{TIMESTEP}" gravity="0 0 0"/>
  <worldbody>{_motor("m1", -0.05)}{_motor("m2", 0.05)}
    <body name="out">
      <joint name="out" type="hinge" axis="0 0 1" armature="{INERTIA}"/>
      <geom type="capsule" fromto="0 0 0 0 0.04 0" size="0.004" mass="1e-6"/>
    </body>
  </worldbody>
  <tendon>
    <fixed name="rollers">
      <joint joint="m1" coef="0.5"/><joint joint="m2" coef="-0.5"/><joint joint="out" coef="-1"/>
    </fixed>
  </tendon>
  <equality><tendon tendon1="rollers" solref="0.0005 1"/></equality>
  <actuator>
    <velocity name="m1" joint="m1" kv="{KV}"/>
    <velocity name="m2" joint="m2" kv="{KV}"/>
  </actuator>
</mujoco>"""


@dataclass
class Ramp:
    command: np.ndarray  # rad/s, the output speed asked for, every ms
    usual: np.ndarray  # rad/s, the usual drive's output speed
    twin: np.ndarray  # rad/s, the twin drive's output speed
    usual_follows_from: float  # rad/s: the lowest |command| from which on the usual drive follows
    twin_follows_from: float

    @property
    def usual_lag(self) -> float:
        return lag(self.command, self.usual, self.usual_follows_from)

    @property
    def twin_lag(self) -> float:
        return lag(self.command, self.twin, self.twin_follows_from)

    def summary(self) -> dict[str, float]:
        return {
            "usual_follows_from_rad_s": self.usual_follows_from,
            "twin_follows_from_rad_s": self.twin_follows_from,
            "usual_lag_rad_s": self.usual_lag,
            "twin_lag_rad_s": self.twin_lag,
            "stick_band_rad_s": COULOMB / KV,
            "kv_nms_per_rad": KV,
        }


def ramp(peak: float = 0.03, seconds: float = 6.0, sample_s: float = 0.001) -> Ramp:
    """Both drives under the same speed command ramping from -peak to +peak (Figs. 12 and 13)."""
    usual = mujoco.MjModel.from_xml_string(usual_xml())
    twin = mujoco.MjModel.from_xml_string(twin_xml())
    du, dt = mujoco.MjData(usual), mujoco.MjData(twin)
    out = twin.joint("out").dofadr[0]
    # the twin drive's motors are brought up to speed first (its output stays where it is)
    dt.ctrl[:] = (BIAS - peak, BIAS + peak)
    mujoco.mj_step(twin, dt, nstep=int(0.2 / TIMESTEP))
    per = round(sample_s / TIMESTEP)
    n = round(seconds / sample_s)
    cmd = np.linspace(-peak, peak, n)
    u_speed, t_speed = np.empty(n), np.empty(n)
    for i, w in enumerate(cmd):
        du.ctrl[0] = w
        dt.ctrl[:] = (BIAS + w, BIAS - w)
        mujoco.mj_step(usual, du, nstep=per)
        mujoco.mj_step(twin, dt, nstep=per)
        u_speed[i], t_speed[i] = du.qvel[0], dt.qvel[out]
    return Ramp(cmd, u_speed, t_speed, follows_from(cmd, u_speed), follows_from(cmd, t_speed))


def follows_from(cmd: np.ndarray, speed: np.ndarray, within: float = 0.5) -> float:
    """The lowest |command| from which on, at every larger one, the drive turns the right way at no
    less than `within` of the command: below it the drive stands still or lags badly."""
    bad = np.abs(cmd)[(speed * np.sign(cmd) < within * np.abs(cmd)) & (cmd != 0)]
    step = float(np.abs(np.diff(cmd)).max())
    return float(bad.max() + step) if bad.size else step


def lag(cmd: np.ndarray, speed: np.ndarray, follows_from: float) -> float:
    """How far the drive's speed stays behind the command where it follows (median |command - speed|
    over |command| >= follows_from, rad/s): a friction-loaded servo's steady error, Coulomb / K_v."""
    on = np.abs(cmd) >= follows_from
    return float(np.median(np.abs(cmd[on] - speed[on]))) if on.any() else float("nan")


def standing_band(cmd: np.ndarray, speed: np.ndarray, still: float = 1e-4) -> float:
    """The largest |command| (rad/s) at which the drive stands still (|speed| under `still` and a tenth
    of the command); 0: never."""
    stuck = np.abs(cmd)[(np.abs(speed) < np.minimum(still, 0.1 * np.abs(cmd))) & (cmd != 0)]
    return float(stuck.max()) if stuck.size else 0.0
