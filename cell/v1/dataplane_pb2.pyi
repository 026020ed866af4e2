from google.protobuf.internal import containers as _containers
from google.protobuf import descriptor as _descriptor
from google.protobuf import message as _message
from collections.abc import Iterable as _Iterable, Mapping as _Mapping
from typing import ClassVar as _ClassVar, Optional as _Optional, Union as _Union

DESCRIPTOR: _descriptor.FileDescriptor

class TrajectoryPoints(_message.Message):
    __slots__ = ("robot_id", "id", "next_id", "duration_s", "joints", "positions", "velocities")
    ROBOT_ID_FIELD_NUMBER: _ClassVar[int]
    ID_FIELD_NUMBER: _ClassVar[int]
    NEXT_ID_FIELD_NUMBER: _ClassVar[int]
    DURATION_S_FIELD_NUMBER: _ClassVar[int]
    JOINTS_FIELD_NUMBER: _ClassVar[int]
    POSITIONS_FIELD_NUMBER: _ClassVar[int]
    VELOCITIES_FIELD_NUMBER: _ClassVar[int]
    robot_id: _containers.RepeatedScalarFieldContainer[int]
    id: _containers.RepeatedScalarFieldContainer[int]
    next_id: _containers.RepeatedScalarFieldContainer[int]
    duration_s: _containers.RepeatedScalarFieldContainer[float]
    joints: _containers.RepeatedScalarFieldContainer[int]
    positions: _containers.RepeatedScalarFieldContainer[float]
    velocities: _containers.RepeatedScalarFieldContainer[float]
    def __init__(self, robot_id: _Optional[_Iterable[int]] = ..., id: _Optional[_Iterable[int]] = ..., next_id: _Optional[_Iterable[int]] = ..., duration_s: _Optional[_Iterable[float]] = ..., joints: _Optional[_Iterable[int]] = ..., positions: _Optional[_Iterable[float]] = ..., velocities: _Optional[_Iterable[float]] = ...) -> None: ...

class TpKeys(_message.Message):
    __slots__ = ("robot_id", "id")
    ROBOT_ID_FIELD_NUMBER: _ClassVar[int]
    ID_FIELD_NUMBER: _ClassVar[int]
    robot_id: _containers.RepeatedScalarFieldContainer[int]
    id: _containers.RepeatedScalarFieldContainer[int]
    def __init__(self, robot_id: _Optional[_Iterable[int]] = ..., id: _Optional[_Iterable[int]] = ...) -> None: ...

class TableUpdate(_message.Message):
    __slots__ = ("insert", "remove", "switches", "registers", "flush_robots", "controller")
    INSERT_FIELD_NUMBER: _ClassVar[int]
    REMOVE_FIELD_NUMBER: _ClassVar[int]
    SWITCHES_FIELD_NUMBER: _ClassVar[int]
    REGISTERS_FIELD_NUMBER: _ClassVar[int]
    FLUSH_ROBOTS_FIELD_NUMBER: _ClassVar[int]
    CONTROLLER_FIELD_NUMBER: _ClassVar[int]
    insert: TrajectoryPoints
    remove: TpKeys
    switches: _containers.RepeatedCompositeFieldContainer[SwitchEntry]
    registers: _containers.RepeatedCompositeFieldContainer[RegisterEntry]
    flush_robots: _containers.RepeatedScalarFieldContainer[int]
    controller: int
    def __init__(self, insert: _Optional[_Union[TrajectoryPoints, _Mapping]] = ..., remove: _Optional[_Union[TpKeys, _Mapping]] = ..., switches: _Optional[_Iterable[_Union[SwitchEntry, _Mapping]]] = ..., registers: _Optional[_Iterable[_Union[RegisterEntry, _Mapping]]] = ..., flush_robots: _Optional[_Iterable[int]] = ..., controller: _Optional[int] = ...) -> None: ...

class SwitchEntry(_message.Message):
    __slots__ = ("robot_id", "tp_id", "next_id", "unset")
    ROBOT_ID_FIELD_NUMBER: _ClassVar[int]
    TP_ID_FIELD_NUMBER: _ClassVar[int]
    NEXT_ID_FIELD_NUMBER: _ClassVar[int]
    UNSET_FIELD_NUMBER: _ClassVar[int]
    robot_id: int
    tp_id: int
    next_id: int
    unset: bool
    def __init__(self, robot_id: _Optional[int] = ..., tp_id: _Optional[int] = ..., next_id: _Optional[int] = ..., unset: _Optional[bool] = ...) -> None: ...

class RegisterEntry(_message.Message):
    __slots__ = ("robot_id", "tp_id", "next_time_ns", "clear")
    ROBOT_ID_FIELD_NUMBER: _ClassVar[int]
    TP_ID_FIELD_NUMBER: _ClassVar[int]
    NEXT_TIME_NS_FIELD_NUMBER: _ClassVar[int]
    CLEAR_FIELD_NUMBER: _ClassVar[int]
    robot_id: int
    tp_id: int
    next_time_ns: int
    clear: bool
    def __init__(self, robot_id: _Optional[int] = ..., tp_id: _Optional[int] = ..., next_time_ns: _Optional[int] = ..., clear: _Optional[bool] = ...) -> None: ...

class UpdateReply(_message.Message):
    __slots__ = ("inserted", "removed", "loaded", "capacity", "apply_us", "now_ns", "total_ms", "boot_id")
    INSERTED_FIELD_NUMBER: _ClassVar[int]
    REMOVED_FIELD_NUMBER: _ClassVar[int]
    LOADED_FIELD_NUMBER: _ClassVar[int]
    CAPACITY_FIELD_NUMBER: _ClassVar[int]
    APPLY_US_FIELD_NUMBER: _ClassVar[int]
    NOW_NS_FIELD_NUMBER: _ClassVar[int]
    TOTAL_MS_FIELD_NUMBER: _ClassVar[int]
    BOOT_ID_FIELD_NUMBER: _ClassVar[int]
    inserted: int
    removed: int
    loaded: int
    capacity: int
    apply_us: float
    now_ns: int
    total_ms: float
    boot_id: int
    def __init__(self, inserted: _Optional[int] = ..., removed: _Optional[int] = ..., loaded: _Optional[int] = ..., capacity: _Optional[int] = ..., apply_us: _Optional[float] = ..., now_ns: _Optional[int] = ..., total_ms: _Optional[float] = ..., boot_id: _Optional[int] = ...) -> None: ...

class MergeRequest(_message.Message):
    __slots__ = ("robot_ids",)
    ROBOT_IDS_FIELD_NUMBER: _ClassVar[int]
    robot_ids: _containers.RepeatedScalarFieldContainer[int]
    def __init__(self, robot_ids: _Optional[_Iterable[int]] = ...) -> None: ...

class MergeReply(_message.Message):
    __slots__ = ("entity",)
    ENTITY_FIELD_NUMBER: _ClassVar[int]
    entity: int
    def __init__(self, entity: _Optional[int] = ...) -> None: ...

class StateRequest(_message.Message):
    __slots__ = ("robot_ids", "robots_only")
    ROBOT_IDS_FIELD_NUMBER: _ClassVar[int]
    ROBOTS_ONLY_FIELD_NUMBER: _ClassVar[int]
    robot_ids: _containers.RepeatedScalarFieldContainer[int]
    robots_only: bool
    def __init__(self, robot_ids: _Optional[_Iterable[int]] = ..., robots_only: _Optional[bool] = ...) -> None: ...

class RobotPlaneState(_message.Message):
    __slots__ = ("robot_id", "entity", "tp_id", "next_time_ns", "position", "velocity", "status_ns", "dropped_ns", "stalled", "dropped_why", "stopped", "controller")
    ROBOT_ID_FIELD_NUMBER: _ClassVar[int]
    ENTITY_FIELD_NUMBER: _ClassVar[int]
    TP_ID_FIELD_NUMBER: _ClassVar[int]
    NEXT_TIME_NS_FIELD_NUMBER: _ClassVar[int]
    POSITION_FIELD_NUMBER: _ClassVar[int]
    VELOCITY_FIELD_NUMBER: _ClassVar[int]
    STATUS_NS_FIELD_NUMBER: _ClassVar[int]
    DROPPED_NS_FIELD_NUMBER: _ClassVar[int]
    STALLED_FIELD_NUMBER: _ClassVar[int]
    DROPPED_WHY_FIELD_NUMBER: _ClassVar[int]
    STOPPED_FIELD_NUMBER: _ClassVar[int]
    CONTROLLER_FIELD_NUMBER: _ClassVar[int]
    robot_id: int
    entity: int
    tp_id: int
    next_time_ns: int
    position: _containers.RepeatedScalarFieldContainer[float]
    velocity: _containers.RepeatedScalarFieldContainer[float]
    status_ns: int
    dropped_ns: int
    stalled: bool
    dropped_why: str
    stopped: bool
    controller: int
    def __init__(self, robot_id: _Optional[int] = ..., entity: _Optional[int] = ..., tp_id: _Optional[int] = ..., next_time_ns: _Optional[int] = ..., position: _Optional[_Iterable[float]] = ..., velocity: _Optional[_Iterable[float]] = ..., status_ns: _Optional[int] = ..., dropped_ns: _Optional[int] = ..., stalled: _Optional[bool] = ..., dropped_why: _Optional[str] = ..., stopped: _Optional[bool] = ..., controller: _Optional[int] = ...) -> None: ...

class DataplaneState(_message.Message):
    __slots__ = ("now_ns", "loaded", "capacity", "robots", "counters", "boot_id", "realtime_offset_ns")
    class CountersEntry(_message.Message):
        __slots__ = ("key", "value")
        KEY_FIELD_NUMBER: _ClassVar[int]
        VALUE_FIELD_NUMBER: _ClassVar[int]
        key: str
        value: float
        def __init__(self, key: _Optional[str] = ..., value: _Optional[float] = ...) -> None: ...
    NOW_NS_FIELD_NUMBER: _ClassVar[int]
    LOADED_FIELD_NUMBER: _ClassVar[int]
    CAPACITY_FIELD_NUMBER: _ClassVar[int]
    ROBOTS_FIELD_NUMBER: _ClassVar[int]
    COUNTERS_FIELD_NUMBER: _ClassVar[int]
    BOOT_ID_FIELD_NUMBER: _ClassVar[int]
    REALTIME_OFFSET_NS_FIELD_NUMBER: _ClassVar[int]
    now_ns: int
    loaded: int
    capacity: int
    robots: _containers.RepeatedCompositeFieldContainer[RobotPlaneState]
    counters: _containers.ScalarMap[str, float]
    boot_id: int
    realtime_offset_ns: int
    def __init__(self, now_ns: _Optional[int] = ..., loaded: _Optional[int] = ..., capacity: _Optional[int] = ..., robots: _Optional[_Iterable[_Union[RobotPlaneState, _Mapping]]] = ..., counters: _Optional[_Mapping[str, float]] = ..., boot_id: _Optional[int] = ..., realtime_offset_ns: _Optional[int] = ...) -> None: ...

class Constants(_message.Message):
    __slots__ = ("c1", "c2", "n_bits", "v_max")
    C1_FIELD_NUMBER: _ClassVar[int]
    C2_FIELD_NUMBER: _ClassVar[int]
    N_BITS_FIELD_NUMBER: _ClassVar[int]
    V_MAX_FIELD_NUMBER: _ClassVar[int]
    c1: _containers.RepeatedScalarFieldContainer[float]
    c2: _containers.RepeatedScalarFieldContainer[float]
    n_bits: int
    v_max: _containers.RepeatedScalarFieldContainer[float]
    def __init__(self, c1: _Optional[_Iterable[float]] = ..., c2: _Optional[_Iterable[float]] = ..., n_bits: _Optional[int] = ..., v_max: _Optional[_Iterable[float]] = ...) -> None: ...

class ConstantsReply(_message.Message):
    __slots__ = ("transform_entries", "limit_entries", "build_ms")
    TRANSFORM_ENTRIES_FIELD_NUMBER: _ClassVar[int]
    LIMIT_ENTRIES_FIELD_NUMBER: _ClassVar[int]
    BUILD_MS_FIELD_NUMBER: _ClassVar[int]
    transform_entries: int
    limit_entries: int
    build_ms: float
    def __init__(self, transform_entries: _Optional[int] = ..., limit_entries: _Optional[int] = ..., build_ms: _Optional[float] = ...) -> None: ...
