from google.protobuf.internal import containers as _containers
from google.protobuf import descriptor as _descriptor
from google.protobuf import message as _message
from collections.abc import Iterable as _Iterable
from typing import ClassVar as _ClassVar, Optional as _Optional

DESCRIPTOR: _descriptor.FileDescriptor

class VisionRequest(_message.Message):
    __slots__ = ("id", "t_ns")
    ID_FIELD_NUMBER: _ClassVar[int]
    T_NS_FIELD_NUMBER: _ClassVar[int]
    id: str
    t_ns: int
    def __init__(self, id: _Optional[str] = ..., t_ns: _Optional[int] = ...) -> None: ...

class VisionReply(_message.Message):
    __slots__ = ("id", "found", "sharpness", "reason", "frame_t_ns", "request_t_ns", "processed_ns", "roi", "truth_distance_mm")
    ID_FIELD_NUMBER: _ClassVar[int]
    FOUND_FIELD_NUMBER: _ClassVar[int]
    SHARPNESS_FIELD_NUMBER: _ClassVar[int]
    REASON_FIELD_NUMBER: _ClassVar[int]
    FRAME_T_NS_FIELD_NUMBER: _ClassVar[int]
    REQUEST_T_NS_FIELD_NUMBER: _ClassVar[int]
    PROCESSED_NS_FIELD_NUMBER: _ClassVar[int]
    ROI_FIELD_NUMBER: _ClassVar[int]
    TRUTH_DISTANCE_MM_FIELD_NUMBER: _ClassVar[int]
    id: str
    found: bool
    sharpness: float
    reason: str
    frame_t_ns: int
    request_t_ns: int
    processed_ns: int
    roi: _containers.RepeatedScalarFieldContainer[int]
    truth_distance_mm: float
    def __init__(self, id: _Optional[str] = ..., found: _Optional[bool] = ..., sharpness: _Optional[float] = ..., reason: _Optional[str] = ..., frame_t_ns: _Optional[int] = ..., request_t_ns: _Optional[int] = ..., processed_ns: _Optional[int] = ..., roi: _Optional[_Iterable[int]] = ..., truth_distance_mm: _Optional[float] = ...) -> None: ...

class VisionInfoRequest(_message.Message):
    __slots__ = ()
    def __init__(self) -> None: ...

class CameraInfo(_message.Message):
    __slots__ = ("robot", "position_m", "axis", "focal_mm", "f_number", "focus_mm", "fps", "width_px", "height_px", "frames_per_s")
    ROBOT_FIELD_NUMBER: _ClassVar[int]
    POSITION_M_FIELD_NUMBER: _ClassVar[int]
    AXIS_FIELD_NUMBER: _ClassVar[int]
    FOCAL_MM_FIELD_NUMBER: _ClassVar[int]
    F_NUMBER_FIELD_NUMBER: _ClassVar[int]
    FOCUS_MM_FIELD_NUMBER: _ClassVar[int]
    FPS_FIELD_NUMBER: _ClassVar[int]
    WIDTH_PX_FIELD_NUMBER: _ClassVar[int]
    HEIGHT_PX_FIELD_NUMBER: _ClassVar[int]
    FRAMES_PER_S_FIELD_NUMBER: _ClassVar[int]
    robot: str
    position_m: _containers.RepeatedScalarFieldContainer[float]
    axis: _containers.RepeatedScalarFieldContainer[float]
    focal_mm: float
    f_number: float
    focus_mm: float
    fps: float
    width_px: int
    height_px: int
    frames_per_s: float
    def __init__(self, robot: _Optional[str] = ..., position_m: _Optional[_Iterable[float]] = ..., axis: _Optional[_Iterable[float]] = ..., focal_mm: _Optional[float] = ..., f_number: _Optional[float] = ..., focus_mm: _Optional[float] = ..., fps: _Optional[float] = ..., width_px: _Optional[int] = ..., height_px: _Optional[int] = ..., frames_per_s: _Optional[float] = ...) -> None: ...

class VisionImage(_message.Message):
    __slots__ = ("t_ns", "jpeg", "width_px", "height_px")
    T_NS_FIELD_NUMBER: _ClassVar[int]
    JPEG_FIELD_NUMBER: _ClassVar[int]
    WIDTH_PX_FIELD_NUMBER: _ClassVar[int]
    HEIGHT_PX_FIELD_NUMBER: _ClassVar[int]
    t_ns: int
    jpeg: bytes
    width_px: int
    height_px: int
    def __init__(self, t_ns: _Optional[int] = ..., jpeg: _Optional[bytes] = ..., width_px: _Optional[int] = ..., height_px: _Optional[int] = ...) -> None: ...
