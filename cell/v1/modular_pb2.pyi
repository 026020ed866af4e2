from google.protobuf.internal import containers as _containers
from google.protobuf import descriptor as _descriptor
from google.protobuf import message as _message
from collections.abc import Iterable as _Iterable, Mapping as _Mapping
from typing import ClassVar as _ClassVar, Optional as _Optional, Union as _Union

DESCRIPTOR: _descriptor.FileDescriptor

class ModularMoveRequest(_message.Message):
    __slots__ = ("joints", "tool", "path", "speed")
    JOINTS_FIELD_NUMBER: _ClassVar[int]
    TOOL_FIELD_NUMBER: _ClassVar[int]
    PATH_FIELD_NUMBER: _ClassVar[int]
    SPEED_FIELD_NUMBER: _ClassVar[int]
    joints: _containers.RepeatedScalarFieldContainer[float]
    tool: _containers.RepeatedScalarFieldContainer[float]
    path: str
    speed: float
    def __init__(self, joints: _Optional[_Iterable[float]] = ..., tool: _Optional[_Iterable[float]] = ..., path: _Optional[str] = ..., speed: _Optional[float] = ...) -> None: ...

class ModularMoveReply(_message.Message):
    __slots__ = ("path", "duration_s", "tool_error_mm_max", "tool_error_mm_rms", "guessed", "cycles")
    PATH_FIELD_NUMBER: _ClassVar[int]
    DURATION_S_FIELD_NUMBER: _ClassVar[int]
    TOOL_ERROR_MM_MAX_FIELD_NUMBER: _ClassVar[int]
    TOOL_ERROR_MM_RMS_FIELD_NUMBER: _ClassVar[int]
    GUESSED_FIELD_NUMBER: _ClassVar[int]
    CYCLES_FIELD_NUMBER: _ClassVar[int]
    path: str
    duration_s: float
    tool_error_mm_max: float
    tool_error_mm_rms: float
    guessed: int
    cycles: int
    def __init__(self, path: _Optional[str] = ..., duration_s: _Optional[float] = ..., tool_error_mm_max: _Optional[float] = ..., tool_error_mm_rms: _Optional[float] = ..., guessed: _Optional[int] = ..., cycles: _Optional[int] = ...) -> None: ...

class ModularModuleRequest(_message.Message):
    __slots__ = ("module",)
    MODULE_FIELD_NUMBER: _ClassVar[int]
    module: str
    def __init__(self, module: _Optional[str] = ...) -> None: ...

class ModularStatusRequest(_message.Message):
    __slots__ = ()
    def __init__(self) -> None: ...

class ModuleStatus(_message.Message):
    __slots__ = ("name", "state", "guessed", "where", "clock_offset_us")
    NAME_FIELD_NUMBER: _ClassVar[int]
    STATE_FIELD_NUMBER: _ClassVar[int]
    GUESSED_FIELD_NUMBER: _ClassVar[int]
    WHERE_FIELD_NUMBER: _ClassVar[int]
    CLOCK_OFFSET_US_FIELD_NUMBER: _ClassVar[int]
    name: str
    state: str
    guessed: int
    where: str
    clock_offset_us: float
    def __init__(self, name: _Optional[str] = ..., state: _Optional[str] = ..., guessed: _Optional[int] = ..., where: _Optional[str] = ..., clock_offset_us: _Optional[float] = ...) -> None: ...

class ModularStatus(_message.Message):
    __slots__ = ("modules", "cycles", "late_cycles", "cycle_us_mean", "cycle_us_max", "q", "tool", "motion", "stopped", "transport", "period_ms")
    MODULES_FIELD_NUMBER: _ClassVar[int]
    CYCLES_FIELD_NUMBER: _ClassVar[int]
    LATE_CYCLES_FIELD_NUMBER: _ClassVar[int]
    CYCLE_US_MEAN_FIELD_NUMBER: _ClassVar[int]
    CYCLE_US_MAX_FIELD_NUMBER: _ClassVar[int]
    Q_FIELD_NUMBER: _ClassVar[int]
    TOOL_FIELD_NUMBER: _ClassVar[int]
    MOTION_FIELD_NUMBER: _ClassVar[int]
    STOPPED_FIELD_NUMBER: _ClassVar[int]
    TRANSPORT_FIELD_NUMBER: _ClassVar[int]
    PERIOD_MS_FIELD_NUMBER: _ClassVar[int]
    modules: _containers.RepeatedCompositeFieldContainer[ModuleStatus]
    cycles: int
    late_cycles: int
    cycle_us_mean: float
    cycle_us_max: float
    q: _containers.RepeatedScalarFieldContainer[float]
    tool: _containers.RepeatedScalarFieldContainer[float]
    motion: str
    stopped: str
    transport: str
    period_ms: float
    def __init__(self, modules: _Optional[_Iterable[_Union[ModuleStatus, _Mapping]]] = ..., cycles: _Optional[int] = ..., late_cycles: _Optional[int] = ..., cycle_us_mean: _Optional[float] = ..., cycle_us_max: _Optional[float] = ..., q: _Optional[_Iterable[float]] = ..., tool: _Optional[_Iterable[float]] = ..., motion: _Optional[str] = ..., stopped: _Optional[str] = ..., transport: _Optional[str] = ..., period_ms: _Optional[float] = ...) -> None: ...

class ModularState(_message.Message):
    __slots__ = ("t_ns", "q", "tool", "tool_ref", "tool_error_mm", "phase_us", "guessed", "states", "frames", "late_cycles", "clock_offset_us", "module_cycle_us")
    T_NS_FIELD_NUMBER: _ClassVar[int]
    Q_FIELD_NUMBER: _ClassVar[int]
    TOOL_FIELD_NUMBER: _ClassVar[int]
    TOOL_REF_FIELD_NUMBER: _ClassVar[int]
    TOOL_ERROR_MM_FIELD_NUMBER: _ClassVar[int]
    PHASE_US_FIELD_NUMBER: _ClassVar[int]
    GUESSED_FIELD_NUMBER: _ClassVar[int]
    STATES_FIELD_NUMBER: _ClassVar[int]
    FRAMES_FIELD_NUMBER: _ClassVar[int]
    LATE_CYCLES_FIELD_NUMBER: _ClassVar[int]
    CLOCK_OFFSET_US_FIELD_NUMBER: _ClassVar[int]
    MODULE_CYCLE_US_FIELD_NUMBER: _ClassVar[int]
    t_ns: int
    q: _containers.RepeatedScalarFieldContainer[float]
    tool: _containers.RepeatedScalarFieldContainer[float]
    tool_ref: _containers.RepeatedScalarFieldContainer[float]
    tool_error_mm: float
    phase_us: _containers.RepeatedScalarFieldContainer[float]
    guessed: _containers.RepeatedScalarFieldContainer[int]
    states: _containers.RepeatedScalarFieldContainer[str]
    frames: _containers.RepeatedScalarFieldContainer[float]
    late_cycles: int
    clock_offset_us: _containers.RepeatedScalarFieldContainer[float]
    module_cycle_us: _containers.RepeatedScalarFieldContainer[float]
    def __init__(self, t_ns: _Optional[int] = ..., q: _Optional[_Iterable[float]] = ..., tool: _Optional[_Iterable[float]] = ..., tool_ref: _Optional[_Iterable[float]] = ..., tool_error_mm: _Optional[float] = ..., phase_us: _Optional[_Iterable[float]] = ..., guessed: _Optional[_Iterable[int]] = ..., states: _Optional[_Iterable[str]] = ..., frames: _Optional[_Iterable[float]] = ..., late_cycles: _Optional[int] = ..., clock_offset_us: _Optional[_Iterable[float]] = ..., module_cycle_us: _Optional[_Iterable[float]] = ...) -> None: ...
