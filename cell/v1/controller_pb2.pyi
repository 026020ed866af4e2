from google.protobuf.internal import containers as _containers
from google.protobuf.internal import enum_type_wrapper as _enum_type_wrapper
from google.protobuf import descriptor as _descriptor
from google.protobuf import message as _message
from collections.abc import Iterable as _Iterable, Mapping as _Mapping
from typing import ClassVar as _ClassVar, Optional as _Optional, Union as _Union

DESCRIPTOR: _descriptor.FileDescriptor

class MoveRequest(_message.Message):
    __slots__ = ("robot", "kind", "frame", "values", "speed", "fine", "start_only")
    class Kind(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
        __slots__ = ()
        JOINTS: _ClassVar[MoveRequest.Kind]
        POSE: _ClassVar[MoveRequest.Kind]
        LINEAR: _ClassVar[MoveRequest.Kind]
    JOINTS: MoveRequest.Kind
    POSE: MoveRequest.Kind
    LINEAR: MoveRequest.Kind
    class Frame(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
        __slots__ = ()
        ABSOLUTE: _ClassVar[MoveRequest.Frame]
        WORLD: _ClassVar[MoveRequest.Frame]
        TOOL: _ClassVar[MoveRequest.Frame]
    ABSOLUTE: MoveRequest.Frame
    WORLD: MoveRequest.Frame
    TOOL: MoveRequest.Frame
    ROBOT_FIELD_NUMBER: _ClassVar[int]
    KIND_FIELD_NUMBER: _ClassVar[int]
    FRAME_FIELD_NUMBER: _ClassVar[int]
    VALUES_FIELD_NUMBER: _ClassVar[int]
    SPEED_FIELD_NUMBER: _ClassVar[int]
    FINE_FIELD_NUMBER: _ClassVar[int]
    START_ONLY_FIELD_NUMBER: _ClassVar[int]
    robot: str
    kind: MoveRequest.Kind
    frame: MoveRequest.Frame
    values: _containers.RepeatedScalarFieldContainer[float]
    speed: float
    fine: bool
    start_only: bool
    def __init__(self, robot: _Optional[str] = ..., kind: _Optional[_Union[MoveRequest.Kind, str]] = ..., frame: _Optional[_Union[MoveRequest.Frame, str]] = ..., values: _Optional[_Iterable[float]] = ..., speed: _Optional[float] = ..., fine: _Optional[bool] = ..., start_only: _Optional[bool] = ...) -> None: ...

class MoveTogetherRequest(_message.Message):
    __slots__ = ("moves",)
    MOVES_FIELD_NUMBER: _ClassVar[int]
    moves: _containers.RepeatedCompositeFieldContainer[MoveRequest]
    def __init__(self, moves: _Optional[_Iterable[_Union[MoveRequest, _Mapping]]] = ...) -> None: ...

class ArriveRequest(_message.Message):
    __slots__ = ("robot", "tolerance_rad", "timeout_s")
    ROBOT_FIELD_NUMBER: _ClassVar[int]
    TOLERANCE_RAD_FIELD_NUMBER: _ClassVar[int]
    TIMEOUT_S_FIELD_NUMBER: _ClassVar[int]
    robot: str
    tolerance_rad: float
    timeout_s: float
    def __init__(self, robot: _Optional[str] = ..., tolerance_rad: _Optional[float] = ..., timeout_s: _Optional[float] = ...) -> None: ...

class MoveReply(_message.Message):
    __slots__ = ("t_start_ns", "t_end_ns", "joints", "pose", "t0_ns", "tps_per_s", "fitted_deviation_mm")
    T_START_NS_FIELD_NUMBER: _ClassVar[int]
    T_END_NS_FIELD_NUMBER: _ClassVar[int]
    JOINTS_FIELD_NUMBER: _ClassVar[int]
    POSE_FIELD_NUMBER: _ClassVar[int]
    T0_NS_FIELD_NUMBER: _ClassVar[int]
    TPS_PER_S_FIELD_NUMBER: _ClassVar[int]
    FITTED_DEVIATION_MM_FIELD_NUMBER: _ClassVar[int]
    t_start_ns: int
    t_end_ns: int
    joints: _containers.RepeatedScalarFieldContainer[float]
    pose: _containers.RepeatedScalarFieldContainer[float]
    t0_ns: int
    tps_per_s: float
    fitted_deviation_mm: float
    def __init__(self, t_start_ns: _Optional[int] = ..., t_end_ns: _Optional[int] = ..., joints: _Optional[_Iterable[float]] = ..., pose: _Optional[_Iterable[float]] = ..., t0_ns: _Optional[int] = ..., tps_per_s: _Optional[float] = ..., fitted_deviation_mm: _Optional[float] = ...) -> None: ...

class JointTrajectory(_message.Message):
    __slots__ = ("robot", "joint_names", "t", "positions", "velocities", "accelerations", "name")
    ROBOT_FIELD_NUMBER: _ClassVar[int]
    JOINT_NAMES_FIELD_NUMBER: _ClassVar[int]
    T_FIELD_NUMBER: _ClassVar[int]
    POSITIONS_FIELD_NUMBER: _ClassVar[int]
    VELOCITIES_FIELD_NUMBER: _ClassVar[int]
    ACCELERATIONS_FIELD_NUMBER: _ClassVar[int]
    NAME_FIELD_NUMBER: _ClassVar[int]
    robot: str
    joint_names: _containers.RepeatedScalarFieldContainer[str]
    t: _containers.RepeatedScalarFieldContainer[float]
    positions: _containers.RepeatedScalarFieldContainer[float]
    velocities: _containers.RepeatedScalarFieldContainer[float]
    accelerations: _containers.RepeatedScalarFieldContainer[float]
    name: str
    def __init__(self, robot: _Optional[str] = ..., joint_names: _Optional[_Iterable[str]] = ..., t: _Optional[_Iterable[float]] = ..., positions: _Optional[_Iterable[float]] = ..., velocities: _Optional[_Iterable[float]] = ..., accelerations: _Optional[_Iterable[float]] = ..., name: _Optional[str] = ...) -> None: ...

class FollowRequest(_message.Message):
    __slots__ = ("trajectories", "speed", "name", "robots", "replace", "start_only")
    TRAJECTORIES_FIELD_NUMBER: _ClassVar[int]
    SPEED_FIELD_NUMBER: _ClassVar[int]
    NAME_FIELD_NUMBER: _ClassVar[int]
    ROBOTS_FIELD_NUMBER: _ClassVar[int]
    REPLACE_FIELD_NUMBER: _ClassVar[int]
    START_ONLY_FIELD_NUMBER: _ClassVar[int]
    trajectories: _containers.RepeatedCompositeFieldContainer[JointTrajectory]
    speed: float
    name: str
    robots: _containers.RepeatedScalarFieldContainer[str]
    replace: bool
    start_only: bool
    def __init__(self, trajectories: _Optional[_Iterable[_Union[JointTrajectory, _Mapping]]] = ..., speed: _Optional[float] = ..., name: _Optional[str] = ..., robots: _Optional[_Iterable[str]] = ..., replace: _Optional[bool] = ..., start_only: _Optional[bool] = ...) -> None: ...

class NameRequest(_message.Message):
    __slots__ = ("name", "trajectories")
    NAME_FIELD_NUMBER: _ClassVar[int]
    TRAJECTORIES_FIELD_NUMBER: _ClassVar[int]
    name: str
    trajectories: _containers.RepeatedCompositeFieldContainer[JointTrajectory]
    def __init__(self, name: _Optional[str] = ..., trajectories: _Optional[_Iterable[_Union[JointTrajectory, _Mapping]]] = ...) -> None: ...

class NameReply(_message.Message):
    __slots__ = ("name", "robots", "points", "duration_s")
    NAME_FIELD_NUMBER: _ClassVar[int]
    ROBOTS_FIELD_NUMBER: _ClassVar[int]
    POINTS_FIELD_NUMBER: _ClassVar[int]
    DURATION_S_FIELD_NUMBER: _ClassVar[int]
    name: str
    robots: _containers.RepeatedScalarFieldContainer[str]
    points: int
    duration_s: float
    def __init__(self, name: _Optional[str] = ..., robots: _Optional[_Iterable[str]] = ..., points: _Optional[int] = ..., duration_s: _Optional[float] = ...) -> None: ...

class StopRequest(_message.Message):
    __slots__ = ("robots",)
    ROBOTS_FIELD_NUMBER: _ClassVar[int]
    robots: _containers.RepeatedScalarFieldContainer[str]
    def __init__(self, robots: _Optional[_Iterable[str]] = ...) -> None: ...

class StopReply(_message.Message):
    __slots__ = ("robots", "t_ns")
    ROBOTS_FIELD_NUMBER: _ClassVar[int]
    T_NS_FIELD_NUMBER: _ClassVar[int]
    robots: _containers.RepeatedScalarFieldContainer[str]
    t_ns: int
    def __init__(self, robots: _Optional[_Iterable[str]] = ..., t_ns: _Optional[int] = ...) -> None: ...

class RobotRequest(_message.Message):
    __slots__ = ("robot",)
    ROBOT_FIELD_NUMBER: _ClassVar[int]
    robot: str
    def __init__(self, robot: _Optional[str] = ...) -> None: ...

class PoseReply(_message.Message):
    __slots__ = ("joints", "pose", "t_ns")
    JOINTS_FIELD_NUMBER: _ClassVar[int]
    POSE_FIELD_NUMBER: _ClassVar[int]
    T_NS_FIELD_NUMBER: _ClassVar[int]
    joints: _containers.RepeatedScalarFieldContainer[float]
    pose: _containers.RepeatedScalarFieldContainer[float]
    t_ns: int
    def __init__(self, joints: _Optional[_Iterable[float]] = ..., pose: _Optional[_Iterable[float]] = ..., t_ns: _Optional[int] = ...) -> None: ...

class Plan(_message.Message):
    __slots__ = ("robot_id", "joints", "t_ns", "positions", "velocities")
    ROBOT_ID_FIELD_NUMBER: _ClassVar[int]
    JOINTS_FIELD_NUMBER: _ClassVar[int]
    T_NS_FIELD_NUMBER: _ClassVar[int]
    POSITIONS_FIELD_NUMBER: _ClassVar[int]
    VELOCITIES_FIELD_NUMBER: _ClassVar[int]
    robot_id: int
    joints: int
    t_ns: _containers.RepeatedScalarFieldContainer[int]
    positions: _containers.RepeatedScalarFieldContainer[float]
    velocities: _containers.RepeatedScalarFieldContainer[float]
    def __init__(self, robot_id: _Optional[int] = ..., joints: _Optional[int] = ..., t_ns: _Optional[_Iterable[int]] = ..., positions: _Optional[_Iterable[float]] = ..., velocities: _Optional[_Iterable[float]] = ...) -> None: ...

class Alternate(_message.Message):
    __slots__ = ("name", "values")
    NAME_FIELD_NUMBER: _ClassVar[int]
    VALUES_FIELD_NUMBER: _ClassVar[int]
    name: str
    values: _containers.RepeatedScalarFieldContainer[float]
    def __init__(self, name: _Optional[str] = ..., values: _Optional[_Iterable[float]] = ...) -> None: ...

class AlternatesRequest(_message.Message):
    __slots__ = ("robot", "alternates", "speed", "every")
    ROBOT_FIELD_NUMBER: _ClassVar[int]
    ALTERNATES_FIELD_NUMBER: _ClassVar[int]
    SPEED_FIELD_NUMBER: _ClassVar[int]
    EVERY_FIELD_NUMBER: _ClassVar[int]
    robot: str
    alternates: _containers.RepeatedCompositeFieldContainer[Alternate]
    speed: float
    every: int
    def __init__(self, robot: _Optional[str] = ..., alternates: _Optional[_Iterable[_Union[Alternate, _Mapping]]] = ..., speed: _Optional[float] = ..., every: _Optional[int] = ...) -> None: ...

class AlternatesReply(_message.Message):
    __slots__ = ("tps_loaded", "branch_points")
    TPS_LOADED_FIELD_NUMBER: _ClassVar[int]
    BRANCH_POINTS_FIELD_NUMBER: _ClassVar[int]
    tps_loaded: int
    branch_points: int
    def __init__(self, tps_loaded: _Optional[int] = ..., branch_points: _Optional[int] = ...) -> None: ...

class TakeAlternate(_message.Message):
    __slots__ = ("robot", "name")
    ROBOT_FIELD_NUMBER: _ClassVar[int]
    NAME_FIELD_NUMBER: _ClassVar[int]
    robot: str
    name: str
    def __init__(self, robot: _Optional[str] = ..., name: _Optional[str] = ...) -> None: ...

class LoopRequest(_message.Message):
    __slots__ = ("robot", "values", "speed", "laps", "start_only")
    ROBOT_FIELD_NUMBER: _ClassVar[int]
    VALUES_FIELD_NUMBER: _ClassVar[int]
    SPEED_FIELD_NUMBER: _ClassVar[int]
    LAPS_FIELD_NUMBER: _ClassVar[int]
    START_ONLY_FIELD_NUMBER: _ClassVar[int]
    robot: str
    values: _containers.RepeatedScalarFieldContainer[float]
    speed: float
    laps: int
    start_only: bool
    def __init__(self, robot: _Optional[str] = ..., values: _Optional[_Iterable[float]] = ..., speed: _Optional[float] = ..., laps: _Optional[int] = ..., start_only: _Optional[bool] = ...) -> None: ...

class LoopReply(_message.Message):
    __slots__ = ("t_start_ns", "lap_ns", "laps")
    T_START_NS_FIELD_NUMBER: _ClassVar[int]
    LAP_NS_FIELD_NUMBER: _ClassVar[int]
    LAPS_FIELD_NUMBER: _ClassVar[int]
    t_start_ns: int
    lap_ns: int
    laps: int
    def __init__(self, t_start_ns: _Optional[int] = ..., lap_ns: _Optional[int] = ..., laps: _Optional[int] = ...) -> None: ...
