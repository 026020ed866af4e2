"""A simulated close-range industrial camera looking at a robot of the cell, rendered by MuJoCo.

The robot's own model file (cell/models) gets the calibration card on
its tool flange and a camera with a ring light; MuJoCo renders it off-screen
(EGL where there is no display) at the robot's joint positions, and the
thin-lens model (cell.vision.optics) blurs the sharp render by the card's
distance from the focus plane and adds sensor noise.  Poses are in the
robot's base frame; the camera looks along `axis` from `position`.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field

import cv2
import numpy as np

from cell.models import get
from cell.models.mjcf import FLANGE_RGBA, mjcf
from cell.vision import optics
from cell.vision.target import HEIGHT_MM, WIDTH_MM, target_image

# joint motion under which the scene counts as still (1e-6 rad moves a 1 m arm's tool 1 um: at the
# default optics a pixel is about 110 um on the card)
STILL_RAD = 1e-6
CARD_MM = 2.0  # the card's thickness on the flange: its face is this far along the tool's z


@dataclass(frozen=True)
class CameraSpec:
    position_m: tuple[float, float, float] = (-0.4919, -0.1333, 0.05)
    axis: tuple[float, float, float] = (0.0, 0.0, 1.0)  # where it looks (unit vector)
    width_px: int = 640
    height_px: int = 480
    lens: optics.ThinLens = field(default_factory=optics.ThinLens)
    noise_dn: float = 1.5


def camera_axes(axis: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The camera's frame for a view along `axis`, as MuJoCo takes it: it looks along its -z, its x
    is right and its y up in the image (the recorder draws its frustum from the same frame)."""
    z = -np.asarray(axis, float) / np.linalg.norm(axis)
    ref = np.array([1.0, 0.0, 0.0]) if abs(z[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x = ref - z * (ref @ z)
    x /= np.linalg.norm(x)
    return x, np.cross(z, x), z


def _xyaxes(axis: np.ndarray) -> str:
    x, y, _ = camera_axes(axis)
    return " ".join(f"{v:.9f}" for v in (*x, *y))


def scene_xml(spec: CameraSpec, model: str = "ur5e") -> str:
    """The robot's model with the card on its flange, the camera and its light."""
    text = mjcf(model)
    w, h, t = WIDTH_MM / 2000, HEIGHT_MM / 2000, CARD_MM / 2000
    flange_z = get(model).d[-1]
    card = f"""
                <body name="card" pos="0 0 {flange_z + t}">
                  <geom name="card" type="box" size="{h} {w} {t}" material="card"/>
                </body>"""
    anchor = re.search(r'<site name="tool" [^>]*/>', text)
    if anchor is None:
        raise ValueError(f"the {model} model has no tool site to put the card on")
    text = text.replace(anchor.group(0), anchor.group(0) + card)
    # the flange behind the card is dark (anodised), so the card's white stands out against it
    text = text.replace(f'rgba="{FLANGE_RGBA}"', 'rgba="0.12 0.12 0.13 1"')
    px, py, pz = spec.position_m
    ax = np.array(spec.axis, float)
    fovy = spec.lens.fovy_deg(spec.height_px)
    light = np.array(spec.position_m) + 0.02 * ax / np.linalg.norm(ax)
    world = f"""
    <camera name="camera" pos="{px} {py} {pz}" xyaxes="{_xyaxes(ax)}" fovy="{fovy:.6f}"/>
    <light name="ring" pos="{light[0]} {light[1]} {light[2]}" dir="{ax[0]} {ax[1]} {ax[2]}"
           diffuse="0.9 0.9 0.9" castshadow="false"/>
    <geom name="camera_body" type="box" pos="{px} {py} {pz - 0.03}" size="0.02 0.02 0.025"
          rgba="0.15 0.15 0.15 1"/>
  </worldbody>"""
    text = text.replace("</worldbody>", world, 1)
    assets = f"""
  <asset>
    <texture name="card" type="2d" file="card.png"/>
    <material name="card" texture="card" rgba="1 1 1 1" specular="0" shininess="0"/>
  </asset>
  <visual>
    <global offwidth="{spec.width_px}" offheight="{spec.height_px}"/>
    <headlight ambient="0.25 0.25 0.25" diffuse="0.3 0.3 0.3"/><quality shadowsize="0"/>
  </visual>
  <worldbody>"""
    return text.replace("<worldbody>", assets, 1)


class Camera:
    """Renders what the camera sees of the robot at joint positions q (rad)."""

    def __init__(self, spec: CameraSpec | None = None, model: str = "ur5e", seed: int = 0) -> None:
        import mujoco  # (its GL backend: see cell/__init__.py)

        self.mujoco = mujoco
        self.spec = spec or CameraSpec()
        ok, png = cv2.imencode(".png", target_image())
        assert ok
        self.model = mujoco.MjModel.from_xml_string(scene_xml(self.spec, model), {"card.png": png.tobytes()})
        self.data = mujoco.MjData(self.model)
        self.renderer = mujoco.Renderer(self.model, self.spec.height_px, self.spec.width_px)
        self.card = self.model.body("card").id
        self.cam = self.model.camera("camera").id
        self.rng = np.random.default_rng(seed)
        self.options = mujoco.MjvOption()
        self.options.sitegroup[:] = 0  # sites are markers, not things a camera sees
        self.nq = 6
        self.noise = optics.ReadNoise((self.spec.height_px, self.spec.width_px), self.spec.noise_dn, self.rng)
        # the last render, blurred, and the joint positions and card distance it shows: a scene that
        # has not moved since is not rendered again (the render and blur are 50 of a frame's 60 ms,
        # which at 10 fps kept half a core busy in a cell where nothing moved)
        self._still: tuple[np.ndarray, np.ndarray, float] | None = None
        self.renders = self.reused = 0

    def close(self) -> None:
        self.renderer.close()

    def card_distance_mm(self) -> float:
        """How far the card's face is from the lens, along the camera's axis (the simulator's truth)."""
        d = self.data
        ax = np.array(self.spec.axis, float)
        ax /= np.linalg.norm(ax)
        # the face towards the camera: the card's centre less half its thickness along the tool's z
        face = d.xpos[self.card] + d.xmat[self.card].reshape(3, 3) @ np.array([0, 0, CARD_MM / 2000])
        return float((face - np.array(self.spec.position_m)) @ ax * 1000.0)

    def capture(self, q: np.ndarray) -> tuple[np.ndarray, float]:
        """A frame (8-bit grayscale) of the robot at q, and the card's true distance (mm).

        Where q is within STILL_RAD of the last render's (joint by joint), that render's blurred image
        is taken again with fresh read noise: the card moved less than a hundredth of a pixel."""
        q = np.asarray(q, float)
        still = self._still
        if still is not None and still[0].shape == q.shape and np.max(np.abs(still[0] - q)) <= STILL_RAD:
            _, img, dist = still
            self.reused += 1
        else:
            img, dist = self._render(q)
            self._still = (q.copy(), img, dist)
            self.renders += 1
        if self.spec.noise_dn > 0:
            img = self.noise.add_to(img)
        return optics.quantise(img), dist

    def _render(self, q: np.ndarray) -> tuple[np.ndarray, float]:
        """The robot at q rendered and blurred by the lens (float32, no noise), and the card's distance."""
        mj = self.mujoco
        self.data.qpos[: self.nq] = q
        mj.mj_kinematics(self.model, self.data)
        mj.mj_camlight(self.model, self.data)  # (cameras and lights are placed by this, not by the above)
        self.renderer.update_scene(self.data, camera=self.cam, scene_option=self.options)
        rgb = self.renderer.render()
        gray = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)
        dist = self.card_distance_mm()
        blur = self.spec.lens.coc_px(dist)
        if not math.isfinite(blur):
            blur = float(max(self.spec.width_px, self.spec.height_px))
        return optics.defocus(gray, blur), dist
