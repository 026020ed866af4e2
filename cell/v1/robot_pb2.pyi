from google.protobuf.internal import containers as _containers
from google.protobuf.internal import enum_type_wrapper as _enum_type_wrapper
from google.protobuf import descriptor as _descriptor
from google.protobuf import message as _message
from collections.abc import Iterable as _Iterable
from typing import ClassVar as _ClassVar, Optional as _Optional, Union as _Union

DESCRIPTOR: _descriptor.FileDescriptor

class RobotAnnounce(_message.Message):
    __slots__ = ("robot_id", "name", "model", "backend", "joints", "q_min", "q_max", "v_max", "a_max", "udp_address", "status_hz", "command_hz", "dataplane", "window_origin_ns")
    ROBOT_ID_FIELD_NUMBER: _ClassVar[int]
    NAME_FIELD_NUMBER: _ClassVar[int]
    MODEL_FIELD_NUMBER: _ClassVar[int]
    BACKEND_FIELD_NUMBER: _ClassVar[int]
    JOINTS_FIELD_NUMBER: _ClassVar[int]
    Q_MIN_FIELD_NUMBER: _ClassVar[int]
    Q_MAX_FIELD_NUMBER: _ClassVar[int]
    V_MAX_FIELD_NUMBER: _ClassVar[int]
    A_MAX_FIELD_NUMBER: _ClassVar[int]
    UDP_ADDRESS_FIELD_NUMBER: _ClassVar[int]
    STATUS_HZ_FIELD_NUMBER: _ClassVar[int]
    COMMAND_HZ_FIELD_NUMBER: _ClassVar[int]
    DATAPLANE_FIELD_NUMBER: _ClassVar[int]
    WINDOW_ORIGIN_NS_FIELD_NUMBER: _ClassVar[int]
    robot_id: int
    name: str
    model: str
    backend: str
    joints: int
    q_min: _containers.RepeatedScalarFieldContainer[float]
    q_max: _containers.RepeatedScalarFieldContainer[float]
    v_max: _containers.RepeatedScalarFieldContainer[float]
    a_max: _containers.RepeatedScalarFieldContainer[float]
    udp_address: str
    status_hz: int
    command_hz: int
    dataplane: str
    window_origin_ns: int
    def __init__(self, robot_id: _Optional[int] = ..., name: _Optional[str] = ..., model: _Optional[str] = ..., backend: _Optional[str] = ..., joints: _Optional[int] = ..., q_min: _Optional[_Iterable[float]] = ..., q_max: _Optional[_Iterable[float]] = ..., v_max: _Optional[_Iterable[float]] = ..., a_max: _Optional[_Iterable[float]] = ..., udp_address: _Optional[str] = ..., status_hz: _Optional[int] = ..., command_hz: _Optional[int] = ..., dataplane: _Optional[str] = ..., window_origin_ns: _Optional[int] = ...) -> None: ...

class RobotTruth(_message.Message):
    __slots__ = ("robot_id", "t_ns", "q", "qd", "tool_pose", "target", "stopped", "tick", "digital_out")
    ROBOT_ID_FIELD_NUMBER: _ClassVar[int]
    T_NS_FIELD_NUMBER: _ClassVar[int]
    Q_FIELD_NUMBER: _ClassVar[int]
    QD_FIELD_NUMBER: _ClassVar[int]
    TOOL_POSE_FIELD_NUMBER: _ClassVar[int]
    TARGET_FIELD_NUMBER: _ClassVar[int]
    STOPPED_FIELD_NUMBER: _ClassVar[int]
    TICK_FIELD_NUMBER: _ClassVar[int]
    DIGITAL_OUT_FIELD_NUMBER: _ClassVar[int]
    robot_id: int
    t_ns: int
    q: _containers.RepeatedScalarFieldContainer[float]
    qd: _containers.RepeatedScalarFieldContainer[float]
    tool_pose: _containers.RepeatedScalarFieldContainer[float]
    target: _containers.RepeatedScalarFieldContainer[float]
    stopped: bool
    tick: int
    digital_out: int
    def __init__(self, robot_id: _Optional[int] = ..., t_ns: _Optional[int] = ..., q: _Optional[_Iterable[float]] = ..., qd: _Optional[_Iterable[float]] = ..., tool_pose: _Optional[_Iterable[float]] = ..., target: _Optional[_Iterable[float]] = ..., stopped: _Optional[bool] = ..., tick: _Optional[int] = ..., digital_out: _Optional[int] = ...) -> None: ...

class GroupTruth(_message.Message):
    __slots__ = ("t_ns", "tick", "joints", "robot_id", "q", "stopped", "answers", "answer_us_mean", "answer_us_max")
    T_NS_FIELD_NUMBER: _ClassVar[int]
    TICK_FIELD_NUMBER: _ClassVar[int]
    JOINTS_FIELD_NUMBER: _ClassVar[int]
    ROBOT_ID_FIELD_NUMBER: _ClassVar[int]
    Q_FIELD_NUMBER: _ClassVar[int]
    STOPPED_FIELD_NUMBER: _ClassVar[int]
    ANSWERS_FIELD_NUMBER: _ClassVar[int]
    ANSWER_US_MEAN_FIELD_NUMBER: _ClassVar[int]
    ANSWER_US_MAX_FIELD_NUMBER: _ClassVar[int]
    t_ns: int
    tick: int
    joints: int
    robot_id: _containers.RepeatedScalarFieldContainer[int]
    q: _containers.RepeatedScalarFieldContainer[float]
    stopped: _containers.RepeatedScalarFieldContainer[bool]
    answers: int
    answer_us_mean: float
    answer_us_max: float
    def __init__(self, t_ns: _Optional[int] = ..., tick: _Optional[int] = ..., joints: _Optional[int] = ..., robot_id: _Optional[_Iterable[int]] = ..., q: _Optional[_Iterable[float]] = ..., stopped: _Optional[_Iterable[bool]] = ..., answers: _Optional[int] = ..., answer_us_mean: _Optional[float] = ..., answer_us_max: _Optional[float] = ...) -> None: ...

class RobotEvent(_message.Message):
    __slots__ = ("robot_id", "name", "kind", "text", "t_ns", "digital_out")
    class Kind(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
        __slots__ = ()
        KIND_UNSPECIFIED: _ClassVar[RobotEvent.Kind]
        KIND_PROTECTIVE_STOP: _ClassVar[RobotEvent.Kind]
        KIND_RESUMED: _ClassVar[RobotEvent.Kind]
        KIND_ESTOP: _ClassVar[RobotEvent.Kind]
        KIND_STOP: _ClassVar[RobotEvent.Kind]
        KIND_STILL: _ClassVar[RobotEvent.Kind]
        KIND_RESUME: _ClassVar[RobotEvent.Kind]
        KIND_PROGRAM: _ClassVar[RobotEvent.Kind]
        KIND_PROGRAM_END: _ClassVar[RobotEvent.Kind]
        KIND_OUTPUTS: _ClassVar[RobotEvent.Kind]
    KIND_UNSPECIFIED: RobotEvent.Kind
    KIND_PROTECTIVE_STOP: RobotEvent.Kind
    KIND_RESUMED: RobotEvent.Kind
    KIND_ESTOP: RobotEvent.Kind
    KIND_STOP: RobotEvent.Kind
    KIND_STILL: RobotEvent.Kind
    KIND_RESUME: RobotEvent.Kind
    KIND_PROGRAM: RobotEvent.Kind
    KIND_PROGRAM_END: RobotEvent.Kind
    KIND_OUTPUTS: RobotEvent.Kind
    ROBOT_ID_FIELD_NUMBER: _ClassVar[int]
    NAME_FIELD_NUMBER: _ClassVar[int]
    KIND_FIELD_NUMBER: _ClassVar[int]
    TEXT_FIELD_NUMBER: _ClassVar[int]
    T_NS_FIELD_NUMBER: _ClassVar[int]
    DIGITAL_OUT_FIELD_NUMBER: _ClassVar[int]
    robot_id: int
    name: str
    kind: RobotEvent.Kind
    text: str
    t_ns: int
    digital_out: int
    def __init__(self, robot_id: _Optional[int] = ..., name: _Optional[str] = ..., kind: _Optional[_Union[RobotEvent.Kind, str]] = ..., text: _Optional[str] = ..., t_ns: _Optional[int] = ..., digital_out: _Optional[int] = ...) -> None: ...

class AnnounceRequest(_message.Message):
    __slots__ = ()
    def __init__(self) -> None: ...

class SilenceRequest(_message.Message):
    __slots__ = ("robot", "seconds")
    ROBOT_FIELD_NUMBER: _ClassVar[int]
    SECONDS_FIELD_NUMBER: _ClassVar[int]
    robot: str
    seconds: float
    def __init__(self, robot: _Optional[str] = ..., seconds: _Optional[float] = ...) -> None: ...

class SilenceReply(_message.Message):
    __slots__ = ("until_ns",)
    UNTIL_NS_FIELD_NUMBER: _ClassVar[int]
    until_ns: int
    def __init__(self, until_ns: _Optional[int] = ...) -> None: ...

class HeldRequest(_message.Message):
    __slots__ = ()
    def __init__(self) -> None: ...

class HeldReply(_message.Message):
    __slots__ = ("robot_ids", "emergency")
    ROBOT_IDS_FIELD_NUMBER: _ClassVar[int]
    EMERGENCY_FIELD_NUMBER: _ClassVar[int]
    robot_ids: _containers.RepeatedScalarFieldContainer[int]
    emergency: _containers.RepeatedScalarFieldContainer[bool]
    def __init__(self, robot_ids: _Optional[_Iterable[int]] = ..., emergency: _Optional[_Iterable[bool]] = ...) -> None: ...
