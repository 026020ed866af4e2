"""The bilateral experiment's manipulators and objects, in MuJoCo.

Both manipulators have the same structure: a two-link arm moving in the
vertical x-z plane (shoulder and elbow pitch), a force sensor between the
forearm and the tip, torque-driven joints.  The joints stand for the paper's
twin drive (cell.teleop.twindrive): viscous friction only, no Coulomb
friction at the output, which is what the twin drive buys; `coulomb_nm`
puts a usual drive's friction back to compare.

The remote arm faces an object: a plate on a spring and damper (a slide
joint's stiffness and damping), touched through a stiff MuJoCo contact.  The
object's law is therefore stated in N/m and N s/m, not in MuJoCo's solver
units: the sponge block is soft and well damped, the wood plate stiff.
"""

from __future__ import annotations

from dataclasses import dataclass

import mujoco
import numpy as np

TIMESTEP = 0.0005  # s: two physics steps per 1 ms control period
SHOULDER_Z = 0.35  # m: the shoulder axis above the floor
L1, L2 = 0.22, 0.22  # m: upper arm and forearm
HOME = (0.30, 0.14)  # m: the tip's (x, z) where the experiment starts
JOINT_DAMPING = 0.01  # N m s / rad: the twin drive's viscous friction, as seen at the joint
CONTACT_SOLREF = (0.002, 1.0)  # contact time constant 2 ms, critically damped: stiff next to the objects
CONTACT_STIFFNESS = (
    78_000.0  # N/m: what that contact gives under this arm's tip (tests/teleop/test_teleop.py)
)


@dataclass(frozen=True)
class ObjectSpec:
    """A compliant object under the remote tip: surface stiffness and damping, and its size."""

    name: str
    stiffness: float  # N/m
    damping: float  # N s/m
    thickness: float  # m, for the drawing
    rgba: tuple[float, float, float, float]


OBJECTS = {
    "sponge": ObjectSpec("sponge", stiffness=400.0, damping=6.0, thickness=0.05, rgba=(0.95, 0.85, 0.3, 1)),
    "wood": ObjectSpec("wood", stiffness=30_000.0, damping=40.0, thickness=0.02, rgba=(0.55, 0.35, 0.2, 1)),
}
TIP_RADIUS = 0.01  # m
SURFACE_Z = HOME[1] - TIP_RADIUS - 0.01  # m: the object's top (spring unloaded), 10 mm below the tip


def arm_xml(obj: ObjectSpec | None = None, coulomb_nm: float = 0.0) -> str:
    """MJCF for one side: the arm, and for the remote side the object under its tip."""
    x0 = HOME[0]
    plate = ""
    if obj is not None:
        base_h = SURFACE_Z - obj.thickness
        r, g, b, a = obj.rgba
        plate = f"""
    <geom name="table" type="box" pos="{x0} 0 {base_h / 2}" size="0.08 0.08 {base_h / 2}"
          rgba="0.5 0.5 0.55 1" contype="0" conaffinity="0"/>
    <body name="object" pos="{x0} 0 {SURFACE_Z}">
      <joint name="object" type="slide" axis="0 0 1" stiffness="{obj.stiffness}" damping="{obj.damping}"/>
      <geom name="object" type="box" pos="0 0 {-obj.thickness / 2}" size="0.05 0.05 {obj.thickness / 2}"
            mass="0.01" rgba="{r} {g} {b} {a}" contype="1" conaffinity="1"
            solref="{CONTACT_SOLREF[0]} {CONTACT_SOLREF[1]}"/>
    </body>"""
    return f"""
<mujoco model="bilateral-arm">
  <option timestep="{TIMESTEP}" integrator="implicitfast"/>
  <default>
    <joint damping="{JOINT_DAMPING}" armature="0.002" frictionloss="{coulomb_nm}"/>
    <geom contype="0" conaffinity="0"/>
  </default>
  <worldbody>
    <geom name="floor" type="plane" size="0.5 0.5 0.01" rgba="0.85 0.85 0.85 1"/>
    <geom name="post" type="cylinder" fromto="0 0 0 0 0 {SHOULDER_Z}" size="0.03" rgba="0.3 0.3 0.35 1"/>
    <body name="upper" pos="0 0 {SHOULDER_Z}">
      <joint name="shoulder" type="hinge" axis="0 1 0"/>
      <geom type="capsule" fromto="0 0 0 {L1} 0 0" size="0.02" mass="0.4" rgba="0.2 0.45 0.8 1"/>
      <body name="fore" pos="{L1} 0 0">
        <joint name="elbow" type="hinge" axis="0 1 0"/>
        <geom type="capsule" fromto="0 0 0 {L2} 0 0" size="0.015" mass="0.25" rgba="0.2 0.6 0.85 1"/>
        <body name="tip" pos="{L2} 0 0">
          <site name="sensor" size="0.005"/>
          <geom name="tip" type="sphere" size="{TIP_RADIUS}" mass="0.02" rgba="0.9 0.3 0.2 1"
                contype="1" conaffinity="1" condim="3" friction="0.3"
                solref="{CONTACT_SOLREF[0]} {CONTACT_SOLREF[1]}"/>
        </body>
      </body>
    </body>{plate}
  </worldbody>
  <actuator>
    <motor name="shoulder" joint="shoulder" ctrlrange="-20 20"/>
    <motor name="elbow" joint="elbow" ctrlrange="-20 20"/>
  </actuator>
  <sensor>
    <force name="tip_force" site="sensor"/>
  </sensor>
</mujoco>"""


def ik(x: float, z: float) -> tuple[float, float]:
    """Joint angles (shoulder, elbow) that put the tip at (x, z), elbow up.

    A hinge about +y turns +x towards -z, so an angle here is minus the usual planar one."""
    dx, dz = x, z - SHOULDER_Z
    c = (dx * dx + dz * dz - L1 * L1 - L2 * L2) / (2 * L1 * L2)
    if not -1.0 <= c <= 1.0:
        raise ValueError(f"({x}, {z}) is out of the arm's reach")
    elbow = -np.arccos(c)  # planar elbow angle, the elbow above the line shoulder-tip
    shoulder = np.arctan2(dz, dx) - np.arctan2(L2 * np.sin(elbow), L1 + L2 * np.cos(elbow))
    return float(-shoulder), float(-elbow)


@dataclass
class TipState:
    """What a side measures of its own arm: tip position, velocity and the external force on it."""

    x: np.ndarray  # (2,) m: x, z
    v: np.ndarray  # (2,) m/s
    f: np.ndarray  # (2,) N: the force the outside (operator, object) exerts on the tip


class Arm:
    """One manipulator in its own MuJoCo world, driven by a tip force through J^T plus gravity
    compensation: the interface a Cartesian force controller has to a torque-driven arm."""

    def __init__(self, obj: ObjectSpec | None = None, coulomb_nm: float = 0.0) -> None:
        self.model = mujoco.MjModel.from_xml_string(arm_xml(obj, coulomb_nm))
        self.data = mujoco.MjData(self.model)
        self.obj = obj
        self.site = self.model.site("sensor").id
        self.tip_body = self.model.body("tip").id
        self._jacp = np.zeros((3, self.model.nv))
        self._adr = self.model.sensor("tip_force").adr[0]
        # the tip body's weight as the sensor sees it at rest (a force sensor is tared with its tool on)
        self._tool_weight = float(self.model.body_subtreemass[self.tip_body] * 9.81)
        self.data.qpos[:2] = ik(*HOME)
        mujoco.mj_forward(self.model, self.data)
        self.hand = np.zeros(2)  # N: an external force on the tip (the operator's hand), world x, z

    def jacobian(self) -> np.ndarray:
        mujoco.mj_jacSite(self.model, self.data, self._jacp, None, self.site)
        return self._jacp[[0, 2], :2]  # x and z rows, the two arm joints

    def tip(self) -> TipState:
        d = self.data
        x = d.site_xpos[self.site][[0, 2]].copy()
        v = self.jacobian() @ d.qvel[:2]
        # the sensor gives the force on the tip body from the forearm, in the site's frame; the outside's
        # force on the tip is its opposite (the tip's own inertia is left in, as with a real sensor)
        f_site = d.sensordata[self._adr : self._adr + 3]
        f_world = d.site_xmat[self.site].reshape(3, 3) @ f_site
        f = -f_world[[0, 2]]
        f[1] += self._tool_weight
        return TipState(x, v, f)

    def drive(self, force: np.ndarray) -> None:
        """Joint torques for a tip force (world x, z), with the arm's gravity and Coriolis compensated."""
        tau = self.jacobian().T @ force + self.data.qfrc_bias[:2]
        self.data.ctrl[:2] = tau

    def step(self, n: int = 2) -> None:
        d = self.data
        if self.hand.any():
            d.xfrc_applied[self.tip_body, [0, 2]] = self.hand
        else:
            d.xfrc_applied[self.tip_body] = 0.0
        mujoco.mj_step(self.model, d, nstep=n)

    def object_deflection(self) -> float:
        """How far the object's surface is pressed in (m), 0 without an object."""
        if self.obj is None:
            return 0.0
        return float(-self.data.qpos[self.model.joint("object").qposadr[0]])
