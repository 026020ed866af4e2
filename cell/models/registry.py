"""RobotModel, the record of one arm, and the registry that names them (see the package's docstring)."""

from __future__ import annotations

from dataclasses import dataclass

Vec = tuple[float, ...]
UR_JOINTS = ("shoulder_pan", "shoulder_lift", "elbow", "wrist_1", "wrist_2", "wrist_3")


@dataclass(frozen=True)
class Drive:
    """A joint's velocity-mode servo in the emulator: position actuator gains, the rotor's reflected
    inertia (armature) and viscous friction."""

    kp: float
    kv: float
    armature: float
    damping: float


@dataclass(frozen=True)
class RobotModel:
    name: str
    title: str
    source: str  # where the parameters come from
    # Denavit-Hartenberg (standard convention, UR's): joint i turns frame {i-1} about z; frame {i} sits
    # at (a_i, 0, d_i) turned Rx(alpha_i); frame {6} is the tool flange
    a: Vec
    d: Vec
    alpha: Vec
    mass: Vec  # kg, link i
    com: tuple[Vec, ...]  # m, link i's centre of mass in frame {i}
    q_min: Vec  # rad
    q_max: Vec
    v_max: Vec  # rad/s
    a_max: Vec  # rad/s^2
    torque: Vec  # N m, each joint's maximum
    drives: tuple[Drive, ...]
    # the links as solid cylinders (UR publishes no inertias): radius, and length along z of the links
    # with a_i = 0 (the others run along x, |a_i| long)
    link_radius: Vec
    link_length: Vec
    # what is drawn (and seen by the camera): per link, a joint housing (radius, half height, z) and,
    # for links with a_i != 0, a capsule along the link (radius, z); the base (radius, half height)
    housings: tuple[Vec, ...]
    beams: tuple[Vec | None, ...]
    base: Vec
    payload_kg: float = 0.0
    reach_m: float = 0.0

    @property
    def joints(self) -> int:
        return len(self.a)

    @property
    def joint_names(self) -> tuple[str, ...]:
        """Its joints as the MJCF names them (UR's: shoulder_pan ... wrist_3)."""
        return UR_JOINTS if self.joints == 6 else tuple(f"joint_{i + 1}" for i in range(self.joints))

    @property
    def ros_joint_names(self) -> tuple[str, ...]:
        """Its joints as ROS names them (ur_description's shoulder_pan_joint ... wrist_3_joint)."""
        return tuple(f"{n}_joint" for n in self.joint_names)

    def __post_init__(self) -> None:
        n = len(self.a)
        per_joint = (
            "d", "alpha", "mass", "com", "q_min", "q_max", "v_max", "a_max", "torque", "drives",
            "link_radius", "link_length", "housings", "beams",
        )  # fmt: skip
        bad = [f for f in per_joint if len(getattr(self, f)) != n]
        if bad:
            raise ValueError(f"robot model {self.name!r}: {', '.join(bad)} must have {n} entries")


MODELS: dict[str, RobotModel] = {}


def register(model: RobotModel) -> RobotModel:
    if MODELS.get(model.name, model) != model:
        raise ValueError(f"two robot models named {model.name!r}")
    MODELS[model.name] = model
    return model


def get(name: str) -> RobotModel:
    """The registered model; KeyError naming the known ones."""
    try:
        return MODELS[name]
    except KeyError:
        raise KeyError(f"unknown robot model {name!r} (known: {', '.join(sorted(MODELS))})") from None
