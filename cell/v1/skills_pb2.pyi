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
