"""A RobotModel as a MuJoCo model (MJCF text), built from its parameters.

Frames: body "link<i>" is DH frame {i-1} turned by joint i about its z axis; its child sits at
(a_i, 0, d_i) turned Rx(alpha_i), so the site "tool" is DH frame {6}, the tool flange.  Centres
of mass are moved from UR's frame {i} into the body frames.  Drives are velocity-mode servos built
from position actuators with damping; the emulator integrates the commanded velocity into the
reference and feeds it forward, ctrl = q_ref + (kv/kp) v_ref, and every link is gravity-compensated
(gravcomp), as the real drives compensate gravity from their own model.
"""

from __future__ import annotations

import math
from functools import cache

from cell.models.registry import RobotModel, get

FLANGE_RGBA = "0.2 0.4 0.8 1"


def _n(*values: float, digits: int = 5) -> str:
    return " ".join(f"{0.0 if abs(v) < 1e-12 else v:.{digits}g}" for v in values)


def _rx(alpha: float, p: tuple[float, ...]) -> tuple[float, float, float]:
    c, s = round(math.cos(alpha), 12), round(math.sin(alpha), 12)
    x, y, z = p
    return x, c * y - s * z, s * y + c * z


def _inertia(m: RobotModel, i: int) -> tuple[float, float, float]:
    """A solid cylinder: along x for links that run along x (a_i != 0), else along z."""
    mass, r = m.mass[i], m.link_radius[i]
    length = abs(m.a[i]) if m.a[i] else m.link_length[i]
    axial, across = mass * r * r / 2, mass * (3 * r * r + length * length) / 12
    return (axial, across, across) if m.a[i] else (across, across, axial)


@cache
def mjcf(name: str, torque: bool = False, timestep: float = 0.002) -> str:
    """The model registered under `name`, as MJCF.  torque: its joints driven by torque motors
    (ctrl in N m within each joint's maximum) with no gravity compensation, for controllers that
    compute the torque themselves (the modular robot, cell.modular)."""
    m = get(name)
    n = m.joints
    names = m.joint_names
    lines = [
        f'<mujoco model="{m.name}-cell{"-torque" if torque else ""}">',
        '  <compiler angle="radian" autolimits="true"/>',
        f'  <option timestep="{_n(timestep)}" integrator="implicitfast" gravity="0 0 -9.81"/>',
        "  <custom>",
        f'    <numeric name="joint_max_velocity" data="{_n(*m.v_max, digits=9)}"/>',
        f'    <numeric name="joint_max_acceleration" data="{_n(*m.a_max, digits=9)}"/>',
        "  </custom>",
        '  <default><geom contype="0" conaffinity="0" rgba="0.7 0.72 0.75 1"/></default>',
        "  <worldbody>",
        f'    <geom name="base" type="cylinder" size="{_n(*m.base)}" pos="0 0 {_n(m.base[1])}" '
        'rgba="0.25 0.27 0.3 1"/>',
    ]
    indent = "    "
    comp = "" if torque else ' gravcomp="1"'
    for i in range(n):
        if i == 0:
            frame = ""
        else:  # placed by the DH row of the joint before
            frame = f' pos="{_n(m.a[i - 1], 0.0, m.d[i - 1])}"'
            if m.alpha[i - 1]:
                h = m.alpha[i - 1] / 2
                frame += f' quat="{_n(math.cos(h), math.sin(h), 0.0, 0.0, digits=8)}"'
        com = _rx(m.alpha[i], m.com[i])
        ipos = (m.a[i] + com[0], com[1], m.d[i] + com[2])
        dr = m.drives[i]
        r, hh, z = m.housings[i]
        rgba = f' rgba="{FLANGE_RGBA}"' if i == n - 1 else ""
        lines += [
            f'{indent}<body name="link{i + 1}"{frame}{comp}>',
            f'{indent}  <joint name="{names[i]}" axis="0 0 1" range="{_n(m.q_min[i], m.q_max[i], digits=6)}" '
            f'armature="{_n(dr.armature)}" damping="{_n(dr.damping)}"/>',
            f'{indent}  <inertial pos="{_n(*ipos)}" mass="{_n(m.mass[i])}" '
            f'diaginertia="{_n(*_inertia(m, i))}"/>',
            f'{indent}  <geom type="cylinder" size="{_n(r, hh)}" pos="0 0 {_n(z)}"{rgba}/>',
        ]
        beam = m.beams[i]
        if beam is not None:
            br, bz = beam
            lines.append(
                f'{indent}  <geom type="capsule" size="{_n(br)}" fromto="{_n(0, 0, bz, m.a[i], 0, bz)}"/>'
            )
        indent += "  "
    lines.append(f'{indent}<site name="tool" pos="{_n(m.a[-1], 0.0, m.d[-1])}" size="0.01"/>')
    for _ in range(n):
        indent = indent[:-2]
        lines.append(f"{indent}</body>")
    lines += ["  </worldbody>", "  <actuator>"]
    for i in range(n):
        dr, t = m.drives[i], m.torque[i]
        if torque:
            lines.append(f'    <motor name="{names[i]}" joint="{names[i]}" ctrlrange="{_n(-t, t)}"/>')
            continue
        lines.append(
            f'    <position name="{names[i]}" joint="{names[i]}" kp="{_n(dr.kp)}" kv="{_n(dr.kv)}" '
            f'forcerange="{_n(-t, t)}"/>'
        )
    lines += ["  </actuator>", "</mujoco>", ""]
    return "\n".join(lines)
