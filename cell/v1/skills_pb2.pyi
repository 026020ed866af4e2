from google.protobuf import descriptor as _descriptor
from google.protobuf import message as _message
from typing import ClassVar as _ClassVar, Optional as _Optional

DESCRIPTOR: _descriptor.FileDescriptor

class SkillTrace(_message.Message):
    __slots__ = ("robot", "id", "skill", "received_ns", "started_ns", "answered_ns", "status", "code", "client")
    ROBOT_FIELD_NUMBER: _ClassVar[int]
    ID_FIELD_NUMBER: _ClassVar[int]
    SKILL_FIELD_NUMBER: _ClassVar[int]
    RECEIVED_NS_FIELD_NUMBER: _ClassVar[int]
    STARTED_NS_FIELD_NUMBER: _ClassVar[int]
    ANSWERED_NS_FIELD_NUMBER: _ClassVar[int]
    STATUS_FIELD_NUMBER: _ClassVar[int]
    CODE_FIELD_NUMBER: _ClassVar[int]
    CLIENT_FIELD_NUMBER: _ClassVar[int]
    robot: str
    id: str
    skill: str
    received_ns: int
    started_ns: int
    answered_ns: int
    status: str
    code: str
    client: str
    def __init__(self, robot: _Optional[str] = ..., id: _Optional[str] = ..., skill: _Optional[str] = ..., received_ns: _Optional[int] = ..., started_ns: _Optional[int] = ..., answered_ns: _Optional[int] = ..., status: _Optional[str] = ..., code: _Optional[str] = ..., client: _Optional[str] = ...) -> None: ...

class AirState(_message.Message):
    __slots__ = ("robot", "on", "t_ns")
    ROBOT_FIELD_NUMBER: _ClassVar[int]
    ON_FIELD_NUMBER: _ClassVar[int]
    T_NS_FIELD_NUMBER: _ClassVar[int]
    robot: str
    on: bool
    t_ns: int
    def __init__(self, robot: _Optional[str] = ..., on: _Optional[bool] = ..., t_ns: _Optional[int] = ...) -> None: ...

class RequestTrace(_message.Message):
    __slots__ = ("robot", "id", "skill", "sent_ns", "received_ns", "status", "code", "t_start", "t_end")
    ROBOT_FIELD_NUMBER: _ClassVar[int]
    ID_FIELD_NUMBER: _ClassVar[int]
    SKILL_FIELD_NUMBER: _ClassVar[int]
    SENT_NS_FIELD_NUMBER: _ClassVar[int]
    RECEIVED_NS_FIELD_NUMBER: _ClassVar[int]
    STATUS_FIELD_NUMBER: _ClassVar[int]
    CODE_FIELD_NUMBER: _ClassVar[int]
    T_START_FIELD_NUMBER: _ClassVar[int]
    T_END_FIELD_NUMBER: _ClassVar[int]
    robot: str
    id: str
    skill: str
    sent_ns: int
    received_ns: int
    status: str
    code: str
    t_start: float
    t_end: float
    def __init__(self, robot: _Optional[str] = ..., id: _Optional[str] = ..., skill: _Optional[str] = ..., sent_ns: _Optional[int] = ..., received_ns: _Optional[int] = ..., status: _Optional[str] = ..., code: _Optional[str] = ..., t_start: _Optional[float] = ..., t_end: _Optional[float] = ...) -> None: ...

class RunEvent(_message.Message):
    __slots__ = ("script", "state", "t_ns", "text")
    SCRIPT_FIELD_NUMBER: _ClassVar[int]
    STATE_FIELD_NUMBER: _ClassVar[int]
    T_NS_FIELD_NUMBER: _ClassVar[int]
    TEXT_FIELD_NUMBER: _ClassVar[int]
    script: str
    state: str
    t_ns: int
    text: str
    def __init__(self, script: _Optional[str] = ..., state: _Optional[str] = ..., t_ns: _Optional[int] = ..., text: _Optional[str] = ...) -> None: ...
