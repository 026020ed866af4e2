"""Universal Robots' e-Series: UR3e, UR5e, UR10e, UR16e.

Sources (Universal Robots' own publications):
- kinematics and dynamics: "DH parameters for calculations of kinematics and dynamics"
  (Universal Robots support article; a, d, alpha, link masses, centres of mass in each DH frame);
- joint ranges: the e-Series user manuals (+/-360 deg every joint) and UR's ROS description
  (Universal_Robots_ROS2_Description, config/<model>/joint_limits.yaml: the elbow +/-180 deg);
- joint speeds: the e-Series datasheets (UR3e 180 deg/s, wrists 360 deg/s; UR5e 180 deg/s;
  UR10e and UR16e 120 deg/s base and shoulder, 180 deg/s the others);
- joint torques: "Max. joint torques" (Universal Robots support article): joint sizes 0-4 are
  12, 28, 56, 150 and 330 N m;
- accelerations: 5 rad/s^2 per joint, as UR's MoveIt configuration limits them (the robot itself
  limits torque, not acceleration); payload and reach from the datasheets.

UR publishes no inertias: each link is a solid cylinder (link_radius, link_length), as the
drawn geometry.  The drives (position servos run in velocity mode, see cell.robot.drive) are tuned
per joint size; the UR5e's are those the cell's benches were measured with.
"""

from __future__ import annotations

import math

from cell.models.registry import Drive, RobotModel, register

PI, TAU = math.pi, 2 * math.pi
ALPHA = (PI / 2, 0.0, 0.0, PI / 2, -PI / 2, 0.0)
Q_MAX = (TAU, TAU, PI, TAU, TAU, TAU)
Q_MIN = tuple(-q for q in Q_MAX)
A_MAX = (5.0,) * 6
SIZE_TORQUE = (12.0, 28.0, 56.0, 150.0, 330.0)
# per joint size: gains that keep the servo's bandwidth about the same as the links it moves grow
SIZE_DRIVE = (
    Drive(kp=350.0, kv=10.0, armature=0.035, damping=0.05),
    Drive(kp=800.0, kv=25.0, armature=0.08, damping=0.1),
    Drive(kp=1600.0, kv=60.0, armature=0.16, damping=0.2),
    Drive(kp=4000.0, kv=200.0, armature=0.4, damping=0.5),
    Drive(kp=8800.0, kv=440.0, armature=0.88, damping=1.1),
)
DEG = PI / 180

# the UR5e's drawn geometry; the others' is it scaled by their size
_HOUSINGS = ((0.06, 0.06, 0.1), (0.06, 0.07, 0.07), (0.05, 0.06, 0.07), (0.045, 0.06, 0.08),
             (0.045, 0.05, 0.05), (0.04, 0.04, 0.06))  # fmt: skip
_BEAMS = (None, (0.054, 0.138), (0.04, 0.02), None, None, None)
_RADIUS = (0.06, 0.054, 0.04, 0.045, 0.045, 0.045)
_LENGTH = (0.15, 0.0, 0.0, 0.12, 0.12, 0.03)


def _ur(
    name: str, title: str, scale: float, sizes: tuple[int, ...], speeds_deg: tuple[float, ...], **kw
) -> None:
    register(
        RobotModel(
            name=name,
            title=title,
            source="Universal Robots: DH parameters for calculations of kinematics and dynamics; "
            "e-Series datasheet; Max. joint torques",
            alpha=ALPHA,
            q_min=Q_MIN,
            q_max=Q_MAX,
            v_max=tuple(s * DEG for s in speeds_deg),
            a_max=A_MAX,
            torque=tuple(SIZE_TORQUE[s] for s in sizes),
            drives=tuple(SIZE_DRIVE[s] for s in sizes),
            link_radius=tuple(round(r * scale, 4) for r in _RADIUS),
            link_length=tuple(round(h * scale, 4) for h in _LENGTH),
            housings=tuple(tuple(round(v * scale, 4) for v in h) for h in _HOUSINGS),
            beams=tuple(None if b is None else tuple(round(v * scale, 4) for v in b) for b in _BEAMS),
            base=(round(0.075 * scale, 4), round(0.04 * scale, 4)),
            **kw,
        )
    )


_ur(
    "ur3e", "UR3e", 0.75, (2, 2, 1, 0, 0, 0), (180, 180, 180, 360, 360, 360),
    a=(0.0, -0.24355, -0.2132, 0.0, 0.0, 0.0),
    d=(0.15185, 0.0, 0.0, 0.13105, 0.08535, 0.0921),
    mass=(1.98, 3.4445, 1.437, 0.871, 0.805, 0.261),
    com=((0.0, -0.02, 0.0), (0.13, 0.0, 0.1157), (0.05, 0.0, 0.0238), (0.0, 0.0, 0.01), (0.0, 0.0, 0.01),
         (0.0, 0.0, -0.02)),
    payload_kg=3.0, reach_m=0.5,
)  # fmt: skip
_ur(
    "ur5e", "UR5e", 1.0, (3, 3, 3, 1, 1, 1), (180,) * 6,
    a=(0.0, -0.425, -0.3922, 0.0, 0.0, 0.0),
    d=(0.1625, 0.0, 0.0, 0.1333, 0.0997, 0.0996),
    mass=(3.761, 8.058, 2.846, 1.37, 1.3, 0.365),
    com=((0.0, -0.02561, 0.00193), (0.2125, 0.0, 0.11336), (0.15, 0.0, 0.0265), (0.0, -0.0018, 0.01634),
         (0.0, 0.0018, 0.01634), (0.0, 0.0, -0.001159)),
    payload_kg=5.0, reach_m=0.85,
)  # fmt: skip
_ur(
    "ur10e", "UR10e", 1.3, (4, 4, 3, 2, 2, 2), (120, 120, 180, 180, 180, 180),
    a=(0.0, -0.6127, -0.57155, 0.0, 0.0, 0.0),
    d=(0.1807, 0.0, 0.0, 0.17415, 0.11985, 0.11655),
    mass=(7.369, 13.051, 3.989, 2.1, 1.98, 0.615),
    com=((0.021, -0.027, 0.0), (0.38, 0.0, 0.158), (0.24, 0.0, 0.068), (0.0, 0.007, 0.018),
         (0.0, 0.007, 0.018), (0.0, 0.0, -0.026)),
    payload_kg=12.5, reach_m=1.3,
)  # fmt: skip
_ur(
    "ur16e", "UR16e", 1.3, (4, 4, 3, 2, 2, 2), (120, 120, 180, 180, 180, 180),
    a=(0.0, -0.4784, -0.36, 0.0, 0.0, 0.0),
    d=(0.1807, 0.0, 0.0, 0.17415, 0.11985, 0.11655),
    mass=(7.369, 10.45, 4.321, 2.18, 2.033, 0.907),
    com=((0.0, -0.016, 0.03), (0.302, 0.0, 0.16), (0.194, 0.0, 0.065), (0.0, -0.009, 0.011),
         (0.0, 0.018, 0.012), (0.0, 0.0, -0.044)),
    payload_kg=16.0, reach_m=0.9,
)  # fmt: skip
